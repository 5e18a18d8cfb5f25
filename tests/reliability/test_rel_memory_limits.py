"""The memory a run may use is the least of free memory, the address-space and data limits (``ulimit -v``,
``ulimit -d``) less what the process already maps, and its cgroup's headroom; a run that does not fit under the
binding limit is refused with a message naming it, not an allocator traceback.

Limit parsing runs on fake ``/proc`` and ``/sys/fs/cgroup`` roots; one test sets a real ``RLIMIT_AS`` in a subprocess.
"""

import os
import re
import resource
import subprocess
import sys
from pathlib import Path

import pytest
from rel_helpers import assert_usage_error

import egcbf
from egcbf.io.allocator import Headroom, MemoryLimit, memory_headroom, memory_limits

SRC = str(Path(egcbf.__file__).resolve().parents[1])
GiB, MiB = 2**30, 2**20
INF = resource.RLIM_INFINITY


def _proc(root: Path, available: int, vmsize: int = 0, vmdata: int = 0, cgroup: str = "0::/\n") -> Path:
    """A fake ``/proc``: ``meminfo``, ``self/status`` (sizes in kB) and ``self/cgroup``."""
    (root / "self").mkdir(parents=True)
    (root / "meminfo").write_text(f"MemTotal:       99999999 kB\nMemAvailable:   {available // 1024} kB\n")
    (root / "self" / "status").write_text(
        f"Name:\tpython\nVmSize:\t{vmsize // 1024} kB\nVmData:\t{vmdata // 1024} kB\n"
    )
    (root / "self" / "cgroup").write_text(cgroup)
    return root


def _cgroup(folder: Path, files: dict[str, str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (folder / name).write_text(text)


def _rlimits(**soft: int):
    """A fake ``resource.getrlimit``: ``_rlimits(RLIMIT_AS=...)``, every other limit unlimited."""
    by_number = {getattr(resource, name): value for name, value in soft.items()}
    return lambda which: (by_number.get(which, INF), INF)


def _headroom(tmp_path, proc, **soft) -> Headroom:
    return memory_headroom(proc, tmp_path / "cg", _rlimits(**soft))


# ----------------------------------------------------------------------------------------------------- parsing
def test_without_limits_free_memory_binds(tmp_path):
    proc = _proc(tmp_path / "proc", 8 * GiB, vmsize=3 * GiB)
    free = _headroom(tmp_path, proc)
    assert free == 8 * GiB and free.limit.kind == "free memory"
    assert "8.0 GiB of free memory (MemAvailable" in str(free.limit)


def test_the_address_space_limit_counts_the_virtual_size_already_mapped(tmp_path):
    proc = _proc(tmp_path / "proc", 8 * GiB, vmsize=3 * GiB, vmdata=1 * GiB)
    free = _headroom(tmp_path, proc, RLIMIT_AS=4 * GiB)  # 1 GiB left, although RSS-based checks would say 4
    assert free == 1 * GiB and free.limit.kind == "RLIMIT_AS"
    text = str(free.limit)
    assert "1.0 GiB left under the address-space limit (ulimit -v, RLIMIT_AS) of 4.0 GiB" in text, text
    assert "3.0 GiB (VmSize)" in text


def test_the_data_limit_counts_vmdata(tmp_path):
    proc = _proc(tmp_path / "proc", 8 * GiB, vmsize=3 * GiB, vmdata=1 * GiB)
    free = _headroom(tmp_path, proc, RLIMIT_AS=6 * GiB, RLIMIT_DATA=1 * GiB + 512 * MiB)
    assert free == 512 * MiB and free.limit.kind == "RLIMIT_DATA"
    assert "data-segment limit (ulimit -d, RLIMIT_DATA) of 1.5 GiB" in str(free.limit)


def test_a_limit_below_the_current_size_leaves_nothing(tmp_path):
    proc = _proc(tmp_path / "proc", 8 * GiB, vmsize=3 * GiB)
    assert _headroom(tmp_path, proc, RLIMIT_AS=2 * GiB) == 0


def test_cgroup_v2_limit_less_usage_without_inactive_page_cache(tmp_path):
    proc = _proc(tmp_path / "proc", 8 * GiB, cgroup="0::/user.slice/job\n")
    cg = tmp_path / "cg"
    _cgroup(cg, {"memory.max": "max\n", "memory.current": "123\n"})  # the root: no limit
    _cgroup(cg / "user.slice", {"memory.max": "max\n", "memory.current": "456\n"})
    stat = f"anon 1\ninactive_file {100 * MiB}\nactive_file 5\n"
    _cgroup(
        cg / "user.slice" / "job", {"memory.max": f"{GiB}\n", "memory.current": f"{900 * MiB}\n", "memory.stat": stat}
    )
    free = _headroom(tmp_path, proc)
    assert free == 224 * MiB and free.limit.kind == "cgroup"  # 1024 - (900 - 100) MiB
    text = str(free.limit)
    assert "cgroup memory limit of 1.0 GiB" in text and str(cg / "user.slice" / "job" / "memory.max") in text, text
    assert "800.0 MiB is in use" in text


def test_a_parent_cgroups_smaller_limit_binds(tmp_path):
    proc = _proc(tmp_path / "proc", 8 * GiB, cgroup="0::/a/b\n")
    cg = tmp_path / "cg"
    _cgroup(cg / "a", {"memory.max": f"{2 * GiB}\n", "memory.current": f"{GiB + 512 * MiB}\n"})
    _cgroup(cg / "a" / "b", {"memory.max": "max\n", "memory.current": f"{GiB}\n"})
    free = _headroom(tmp_path, proc)
    assert free == 512 * MiB and str(cg / "a" / "memory.max") in str(free.limit)


def test_cgroup_v1_limit_and_its_no_limit_value(tmp_path):
    proc = _proc(tmp_path / "proc", 8 * GiB, cgroup="4:memory:/docker/abc\n1:cpu,cpuacct:/docker/abc\n0::/\n")
    v1 = tmp_path / "cg" / "memory"
    _cgroup(v1, {"memory.limit_in_bytes": "9223372036854771712\n", "memory.usage_in_bytes": "1\n"})  # "no limit"
    _cgroup(v1 / "docker" / "abc", {"memory.limit_in_bytes": f"{3 * GiB}\n", "memory.usage_in_bytes": f"{2 * GiB}\n",
                                    "memory.stat": f"inactive_file 7\ntotal_inactive_file {GiB}\n"})  # fmt: skip
    free = _headroom(tmp_path, proc)
    assert free == 2 * GiB and "memory.limit_in_bytes" in str(free.limit)
    (v1 / "docker" / "abc" / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    assert _headroom(tmp_path, proc).limit.kind == "free memory"


def test_a_cgroup_path_missing_under_the_mount_falls_back_to_the_root(tmp_path):
    """A container without its own cgroup namespace sees the host's path; its mount is its own cgroup."""
    proc = _proc(tmp_path / "proc", 8 * GiB, cgroup="0::/system.slice/docker-1.scope\n")
    _cgroup(tmp_path / "cg", {"memory.max": f"{GiB}\n", "memory.current": f"{256 * MiB}\n"})
    assert _headroom(tmp_path, proc) == 768 * MiB


def test_nothing_readable_means_no_refusal(tmp_path):
    (tmp_path / "proc").mkdir()
    assert memory_limits(tmp_path / "proc", tmp_path / "cg", _rlimits()) == []
    assert memory_headroom(tmp_path / "proc", tmp_path / "cg", _rlimits()) is None


def test_the_real_machine_has_at_least_free_memory():
    free = memory_headroom()
    assert free is not None and free > 0 and isinstance(free, int)


# ------------------------------------------------------------------------------------------------- the refusal
def test_the_refusal_names_the_binding_limit(cli, tmp_path, tiny_run, monkeypatch):
    import egcbf.cli.checks as checks

    limit = MemoryLimit("RLIMIT_AS", MiB, "the 1.0 MiB left under the address-space limit (ulimit -v, RLIMIT_AS) of "
                        "2.0 GiB, of which this process already uses 2.0 GiB (VmSize)")  # fmt: skip
    monkeypatch.setattr(checks, "available_memory", lambda device: Headroom(limit))
    res = cli("eval", "--checkpoint", tiny_run, "--num-agents", "64", "--area", "2", "--episodes", "1",
              "--max-steps", "3", "--out", tmp_path / "ev", "--no-progress")  # fmt: skip
    assert_usage_error(res, "--num-agents 64", "more than the 1.0 MiB left under the address-space limit", "VmSize")


RUN_UNDER_RLIMIT_AS = """
import re, resource, sys
from egcbf.cli import main
vmsize = int(re.search(r"VmSize:\\s+(\\d+)", open("/proc/self/status").read()).group(1)) * 1024
resource.setrlimit(resource.RLIMIT_AS, (vmsize + (256 << 20), resource.getrlimit(resource.RLIMIT_AS)[1]))
main()
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs /proc (Linux)")
def test_a_run_that_does_not_fit_under_ulimit_v_is_refused_naming_it(tmp_path, tiny_run):
    """With 256 MiB of address space left after the imports, 16 episodes of 256 agents at once (~1 GiB) do not fit,
    although free memory would hold them: refused up front, not a DefaultCPUAllocator traceback mid-run."""
    out = tmp_path / "ev"
    env = {**os.environ, "PYTHONPATH": SRC, "OMP_NUM_THREADS": "1"}
    env.pop("EGCBF_DEBUG", None)
    res = subprocess.run([sys.executable, "-c", RUN_UNDER_RLIMIT_AS, "eval", "--checkpoint", str(tiny_run),
                          "--num-agents", "256", "--area", "2", "--episodes", "16", "--batch", "16", "--max-steps",
                          "3", "--out", str(out), "--no-progress", "--threads", "1"],
                         env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error:")]
    assert res.returncode == 2 and len(errors) == 1, res.stderr[-3000:]
    assert "Traceback" not in res.stderr and "DefaultCPUAllocator" not in res.stderr
    assert "--num-agents 256" in errors[0] and "address-space limit (ulimit -v, RLIMIT_AS)" in errors[0], errors[0]
    assert re.search(r"more than the [\d.]+ MiB left under", errors[0]) and "(VmSize)" in errors[0], errors[0]
    assert not (out / "metrics.json").exists()


RUN_EXPORT_UNDER_RLIMIT_AS = """
import re, resource, sys
from egcbf.cli import main
vmsize = int(re.search(r"VmSize:\\s+(\\d+)", open("/proc/self/status").read()).group(1)) * 1024
resource.setrlimit(resource.RLIMIT_AS, (vmsize + (16 << 20), resource.getrlimit(resource.RLIMIT_AS)[1]))
main()
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs /proc (Linux)")
def test_export_out_of_address_space_is_one_line_and_writes_nothing(tmp_path):
    """A command that runs out of memory anywhere (here ``export``, in its lazy imports, 16 MiB of address space
    left) prints one ``Error:`` line naming the cause and the limit, exit 2, and writes nothing."""
    out = tmp_path / "ctrl.pt"
    ckpt = Path(SRC).parent / "checkpoints" / "egcbf+"
    env = {**os.environ, "PYTHONPATH": SRC, "OMP_NUM_THREADS": "1"}
    env.pop("EGCBF_DEBUG", None)
    res = subprocess.run([sys.executable, "-c", RUN_EXPORT_UNDER_RLIMIT_AS, "export", "--checkpoint", str(ckpt),
                          "--format", "torchscript", "--out", str(out)],
                         env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error:")]
    assert res.returncode == 2 and len(errors) == 1, res.stderr[-3000:]
    assert "Traceback" not in res.stderr and "out of memory" in errors[0] and "ulimit -v" in errors[0]
    assert not out.exists() and not out.with_name("ctrl.pt.json").exists()


def test_a_config_far_larger_than_its_weights_is_refused_before_allocating(cli, tmp_path):
    """``model.hidden: 1e9`` in an edited config.json would allocate tens of GB before the weights are compared:
    refused first, naming the field (eval, export and average alike)."""
    import json
    import shutil

    ckpt = tmp_path / "ckpt"
    shutil.copytree(Path(SRC).parent / "checkpoints" / "egcbf+", ckpt)
    cfg = json.loads((ckpt / "config.json").read_text())
    cfg["model"]["hidden"] = 10**9
    (ckpt / "config.json").write_text(json.dumps(cfg))
    for args in (["eval", "--checkpoint", ckpt, "--num-agents", "4", "--episodes", "1", "--out", tmp_path / "ev"],
                 ["export", "--checkpoint", ckpt, "--format", "torchscript", "--out", tmp_path / "c.pt"],
                 ["average", "--a", ckpt, "--b", ckpt, "--lam", "0.5", "--out", tmp_path / "avg"]):  # fmt: skip
        assert_usage_error(cli(*args), "model.hidden = 1000000000", "does not describe these weights")
