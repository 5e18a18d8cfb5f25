"""egcbf.io.atomic: files and directories are replaced whole, and an interrupted directory swap is recovered."""

import json

import pytest

from egcbf.io.atomic import recover_dir, replace_dir, write_json_atomic, write_text_atomic


def test_write_text_replaces_the_whole_file(tmp_path):
    f = tmp_path / "a.csv"
    f.write_text("old content that is longer")
    write_text_atomic(f, "new")
    assert f.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["a.csv"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    f = tmp_path / "m.json"
    write_json_atomic(f, [1])
    with pytest.raises(TypeError):
        write_json_atomic(f, {"x": object()})  # not JSON: fails before anything is written
    assert json.loads(f.read_text()) == [1] and sorted(p.name for p in tmp_path.iterdir()) == ["m.json"]


def test_replace_dir_into_a_new_place(tmp_path):
    (tmp_path / "d.tmp").mkdir()
    (tmp_path / "d.tmp" / "x").write_text("1")
    assert replace_dir(tmp_path / "d.tmp", tmp_path / "d") == tmp_path / "d"
    assert (tmp_path / "d" / "x").read_text() == "1" and not (tmp_path / "d.tmp").exists()


def test_replace_dir_removes_a_leftover_old(tmp_path):
    for name, text in (("d", "current"), ("d.old", "partial leftover"), ("d.tmp", "new")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "x").write_text(text)
    replace_dir(tmp_path / "d.tmp", tmp_path / "d")
    assert (tmp_path / "d" / "x").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


def test_recover_dir_leaves_a_complete_directory_alone(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d.old").mkdir()
    assert recover_dir(tmp_path / "d") == tmp_path / "d" and (tmp_path / "d.old").exists()


def test_recover_dir_without_anything_is_a_no_op(tmp_path):
    assert recover_dir(tmp_path / "none") == tmp_path / "none"
    assert not (tmp_path / "none").exists()
