"""A full disk or the file-size limit during a write: one error naming the file and the cause, what was written
before intact; a failed render keeps its swarm size's metrics; a killed writer's temporary files are removed.

The limits are real: each case runs in a subprocess with ``RLIMIT_FSIZE`` set (``SIGXFSZ`` ignored, so a write past
it fails with ``EFBIG`` instead of killing the process); a full disk is ``/dev/full`` (``ENOSPC``).
"""

import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import egcbf
from egcbf.io.atomic import WriteError, remove_stale_temporaries, write_json_atomic, write_text_atomic, writing
from egcbf.train.checkpoint import find_checkpoint, load_learner

SRC = str(Path(egcbf.__file__).resolve().parents[1])

#: the prologue of every subprocess: SIGXFSZ ignored, and ``limit(n)`` sets the file-size limit to n bytes
PROLOGUE = """
import json, resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
def limit(n):
    resource.setrlimit(resource.RLIMIT_FSIZE, (n, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
"""


def _python(code: str, *args) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": SRC, "OMP_NUM_THREADS": "1"}
    env.pop("EGCBF_DEBUG", None)
    return subprocess.run([sys.executable, "-c", PROLOGUE + code, *map(str, args)], env=env, capture_output=True,
                          text=True, timeout=120)  # fmt: skip


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture
def run(tiny_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(tiny_run, dst)
    return dst


# ----------------------------------------------------------------------------------------------------- checkpoints
SAVE = """
from egcbf.io.atomic import WriteError
from egcbf.train.checkpoint import find_checkpoint, load_learner, save_best, save_checkpoint
run = sys.argv[1]
learner = load_learner(find_checkpoint(run))
errors, small, large = [], int(sys.argv[2]), int(sys.argv[3])
for n, save in ((small, save_checkpoint), (large, save_checkpoint), (small, save_best)):
    limit(n)
    try:
        save(learner, run, 1.0, {"step": 4}) if save is save_best else save(learner, run, 1.0)
    except WriteError as err:
        errors.append(str(err))
print(json.dumps(errors))
"""


def test_a_checkpoint_save_past_the_file_size_limit_names_the_file_and_keeps_the_old_one(run):
    ckpt = find_checkpoint(run)  # step_000004, saved again (the same step) by the subprocess
    model, state = (ckpt / "model.safetensors").stat().st_size, (ckpt / "training_state.pt").stat().st_size
    assert model < state  # the limits below stop safetensors' write, then torch.save's
    before, best = _digests(ckpt), _digests(run / "best")
    res = _python(SAVE, run, model // 2, (model + state) // 2)
    assert res.returncode == 0, res.stderr
    errors = json.loads(res.stdout.strip().splitlines()[-1])
    assert len(errors) == 3, errors
    for err, name in zip(errors, ("model.safetensors", "training_state.pt", "model.safetensors"), strict=True):
        assert f"/{name}:" in err and "file-size limit" in err and "ulimit -f" in err, err
        assert "unexpected pos" not in err and "SafetensorError" not in err, err
    assert f"{ckpt} was not saved" in errors[0] and f"{run / 'best'} was not saved" in errors[2]
    assert _digests(ckpt) == before and _digests(run / "best") == best  # the old ones are intact
    assert not list(run.rglob("*.tmp")) and not list(run.rglob("*.old"))
    load_learner(ckpt)


def test_train_past_the_file_size_limit_ends_with_one_error_line(tmp_path):
    out = tmp_path / "run"
    code = "from egcbf.cli import main\nlimit(32 << 10)\nmain()"  # config.json, the CSVs fit; best/'s weights do not
    res = _python(code, "train", "--algo", "egcbf+", "--preset", "tiny", "--steps", "2", "--out", out,
                  "--no-progress", "--threads", "1")  # fmt: skip
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error:")]
    assert res.returncode == 1 and len(errors) == 1, res.stderr
    assert "Traceback" not in res.stderr
    assert f"{out / 'best.tmp' / 'model.safetensors'}:" in errors[0] and "file-size limit" in errors[0], errors[0]
    assert not (out / "best.tmp").exists() and (out / "config.json").exists()


# --------------------------------------------------------------------------------------------------------- metrics
METRICS = """
import torch
from egcbf.io.atomic import WriteError, write_json_atomic, writing
from egcbf.train.loop import METRICS_FIELDS, _Logger
from pathlib import Path
out = Path(sys.argv[1])
logger = _Logger(out, 0)  # metrics.csv and scalars.csv with their headers
limit(int(sys.argv[2]))
errors = []
for write in (
    lambda: write_json_atomic(out / "metrics.json", [{"num_agents": n, "safe_rate": 1.0} for n in range(100)]),
    lambda: logger.metrics({k: 0.5 for k in METRICS_FIELDS}),
    lambda: logger.scalars(1, 0.5, {f"loss/term{k}": 0.5 for k in range(100)}),
):
    try:
        write()
    except WriteError as err:
        errors.append(str(err))
try:
    with writing(out / "state.pt"):  # torch.save to a path: its own "unexpected pos" error, diagnosed
        torch.save(torch.zeros(10_000), out / "state.pt")
except WriteError as err:
    errors.append(str(err))
print(json.dumps(errors))
"""


def test_metrics_writes_past_the_file_size_limit_name_the_file_and_keep_what_was_written(tmp_path):
    out = tmp_path / "ev"
    out.mkdir()
    write_json_atomic(out / "metrics.json", [{"num_agents": 4, "safe_rate": 1.0}])
    old = (out / "metrics.json").read_text()
    res = _python(METRICS, out, 100)  # the CSV headers fit, a row more does not
    assert res.returncode == 0, res.stderr
    errors = json.loads(res.stdout.strip().splitlines()[-1])
    names = ("metrics.json", "metrics.csv", "scalars.csv", "state.pt")
    assert len(errors) == len(names), errors
    for err, name in zip(errors, names, strict=True):
        assert f"could not write {out / name}: the file-size limit" in err and "100 B)" in err, err
    assert (out / "metrics.json").read_text() == old  # atomic: the previous metrics are untouched
    assert not list(out.glob(".*.tmp"))


def test_a_render_past_the_file_size_limit_keeps_that_sizes_metrics(tmp_path):
    out = tmp_path / "ev"
    code = "from egcbf.cli import main\nlimit(8 << 10)\nmain()"  # metrics.json, run.json fit; the images do not
    res = _python(code, "eval", "--controller", "nominal", "--num-agents", "4,6", "--area", "2", "--episodes", "1",
                  "--max-steps", "3", "--out", out, "--render", "--no-progress", "--threads", "1")  # fmt: skip
    assert res.returncode == 0, res.stderr
    warnings = [line for line in res.stderr.splitlines() if line.startswith("Warning: could not write")]
    assert len(warnings) == 2 and "Traceback" not in res.stderr, res.stderr
    assert "nominal_N4" in warnings[0] and "file-size limit" in warnings[0] and "metrics of N = 4" in warnings[0]
    assert [r["num_agents"] for r in json.loads((out / "metrics.json").read_text())] == [4, 6]
    run = json.loads((out / "run.json").read_text())
    assert run["finished"] == [4, 6] and run["complete"] is True
    assert not [p.name for p in out.iterdir() if p.suffix in (".gif", ".png")]  # no partial image left


# ----------------------------------------------------------------------------------------------------- full disk
@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_a_full_disk_names_the_file_and_the_cause():
    with pytest.raises(WriteError) as info, writing("/dev/full", "nothing was there"):
        with open("/dev/full", "w") as f:
            f.write("x" * 100)
    assert info.value.errno == errno.ENOSPC and isinstance(info.value, OSError)
    assert str(info.value).startswith("could not write /dev/full: no space left on device (nothing was there); free")


def test_other_errors_pass_unchanged(tmp_path):
    with pytest.raises(PermissionError), writing(tmp_path / "x"):
        raise PermissionError(errno.EACCES, "Permission denied")
    with pytest.raises(ValueError), writing(tmp_path / "x"):
        raise ValueError("not a write error")


# ---------------------------------------------------------------------------------------- stale temporary files
def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_dead_writers_temporary_is_removed_at_the_next_write_and_a_live_ones_kept(tmp_path):
    target = tmp_path / "metrics.json"
    dead, live = _dead_pid(), os.getppid()  # the parent of the test process is alive
    stale = tmp_path / f".metrics.json.{dead}.tmp"
    busy = tmp_path / f".metrics.json.{live}.tmp"
    other = tmp_path / f".run.json.{dead}.tmp"  # another target's: left for that target's next write
    for p in (stale, busy, other):
        p.write_text("partial")
    write_json_atomic(target, [1])
    assert json.loads(target.read_text()) == [1]
    assert not stale.exists() and busy.exists() and other.exists()
    write_text_atomic(tmp_path / "run.json", "{}\n")
    assert not other.exists() and busy.exists()


def test_remove_stale_temporaries_says_what_it_removed(tmp_path):
    dead = _dead_pid()
    stale = tmp_path / f".a.csv.{dead}.tmp"
    stale.write_text("x")
    (tmp_path / ".a.csv.notapid.tmp").write_text("x")
    assert remove_stale_temporaries(tmp_path / "a.csv") == [stale]
    assert (tmp_path / ".a.csv.notapid.tmp").exists()
