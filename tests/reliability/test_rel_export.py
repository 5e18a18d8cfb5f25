"""``egcbf export`` never writes into a checkpoint or training run, nor over a file it was not told to replace:
OUT and its layout file OUT.json are both checked before any work (one ``Error:`` line, exit 2, nothing written)."""

import hashlib
import shutil
from pathlib import Path

import pytest
from rel_helpers import assert_usage_error

ROOT = Path(__file__).resolve().parents[2] / "checkpoints" / "egcbf+"


def _digest(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture
def ckpt(tmp_path):
    dst = tmp_path / "ckpt"
    shutil.copytree(ROOT, dst)
    return dst


@pytest.mark.parametrize(
    "name, extra",
    [("config", []), ("state", []), ("model.safetensors", ["--overwrite"]), ("sub/ctrl.pt", ["--overwrite"])],
)
def test_export_refuses_to_write_inside_a_checkpoint(cli, ckpt, name, extra):
    before = _digest(ckpt)
    res = cli("export", "--checkpoint", ckpt, "--format", "torchscript", "--out", ckpt / name, *extra)
    assert_usage_error(res, "inside the checkpoint", str(ckpt))
    assert _digest(ckpt) == before


def test_export_refuses_to_write_inside_a_training_run(cli, tiny_run):
    res = cli("export", "--checkpoint", tiny_run, "--format", "torchscript", "--out", tiny_run / "ctrl.pt")
    assert_usage_error(res, "inside the checkpoint or training run")
    assert not (tiny_run / "ctrl.pt").exists()


def test_export_refuses_an_existing_layout_file(cli, tmp_path):
    (tmp_path / "results.json").write_text('{"unrelated": 1}')
    res = cli("export", "--checkpoint", ROOT, "--format", "torchscript", "--out", tmp_path / "results")
    assert_usage_error(res, "results.json exists", "--overwrite")
    assert (tmp_path / "results.json").read_text() == '{"unrelated": 1}'
    assert not (tmp_path / "results").exists()


def test_export_refuses_a_layout_path_that_is_a_directory(cli, tmp_path):
    (tmp_path / "ctrl.pt.json").mkdir()
    res = cli("export", "--checkpoint", ROOT, "--format", "torchscript", "--out", tmp_path / "ctrl.pt", "--overwrite")
    assert_usage_error(res, "is a directory")
