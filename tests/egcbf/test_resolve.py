"""egcbf.control.resolve: one function builds every controller from ``METHOD[:FILTER]`` and a checkpoint, reading the
checkpoint's files once; the robots declare their hand-crafted controllers."""

import ast
from pathlib import Path

import pytest
import torch

from egcbf.algo.learner import LearnedController
from egcbf.control import resolve as resolve_module
from egcbf.control.controllers import NominalController, robot_controllers
from egcbf.control.filters import FilterConfig, FilteredController
from egcbf.control.resolve import ControllerError, reads_sensing, resolve
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.robots import ROBOTS, Robot
from egcbf.robots.point_mass_qp import PointMassDCBF
from egcbf.robots.quadrotor.dcbf_qp import DecentralizedCBFQP
from egcbf.train import checkpoint as ckpt_module

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "checkpoints" / "egcbf+"


def test_hand_crafted_controllers_are_the_robots_own():
    assert isinstance(resolve("nominal").controller, NominalController)
    assert isinstance(resolve("dcbf").controller, DecentralizedCBFQP)
    assert isinstance(resolve("dcbf", robot="double_integrator").controller, PointMassDCBF)
    built = resolve("nominal:dcbf")
    assert isinstance(built.controller, FilteredController) and built.filter == "dcbf" and built.checkpoint is None
    for name, cls in ROBOTS.items():
        assert {"nominal", "brisk"} <= set(robot_controllers(name))
        assert set(robot_controllers(name)) - {"nominal", "brisk"} == set(cls().cbf_qps())


def test_a_robot_without_cbf_qps_has_its_nominal_and_brisk_laws_only():
    class Bare(Robot):
        name = "bare-test-robot"

    ROBOTS[Bare.name] = Bare
    try:
        assert set(robot_controllers(Bare.name)) == {"nominal", "brisk"}
        with pytest.raises(ControllerError, match="unknown controller 'dcbf' for the bare-test-robot"):
            resolve("dcbf", robot=Bare.name)
    finally:
        del ROBOTS[Bare.name]


@pytest.mark.parametrize(
    ("name", "checkpoint", "match"),
    [
        ("egcbf+", None, "a learned method needs its checkpoint"),
        ("nominal:cbf", None, "not with cbf"),
        ("dcbf:dcbf", None, "filters a learned policy's commands"),
        ("nominal:bogus", None, "FILTER one of"),
        ("gcbf+", SHIPPED, "holds a egcbf\\+ policy, not gcbf\\+"),
        ("nominal", None, None),
    ],
)
def test_bad_names_are_one_clear_error(name, checkpoint, match):
    if match is None:
        resolve(name)
        return
    with pytest.raises(ControllerError, match=match):
        resolve(name, checkpoint)


def test_a_checkpoints_robot_and_options_are_checked():
    with pytest.raises(ControllerError, match="drives a quadrotor"):
        resolve("policy", SHIPPED, robot="unicycle")
    with pytest.raises(ControllerError, match="set a hand-crafted controller"):
        resolve("policy", SHIPPED, kind="hocbf")
    with pytest.raises(ControllerError, match="settings are of 'prior'"):
        resolve("policy:dcbf", SHIPPED, filter_config=FilterConfig.for_kind("prior"))


def test_a_checkpoint_is_read_once_per_controller_built(monkeypatch):
    """``policy:cbf`` needs the policy and the CBF: both come from one read of each file (the safetensors readers
    that open the file themselves are never called)."""
    reads = []
    real = ckpt_module._read_file
    monkeypatch.setattr(ckpt_module, "_read_file", lambda path: reads.append(Path(path).name) or real(path))
    for name in ("load_file", "safe_open"):
        monkeypatch.setattr(ckpt_module, name, lambda *a, **k: pytest.fail("a second read of the weights"))
    configs = []
    real_config = ckpt_module.read_config
    monkeypatch.setattr(ckpt_module, "read_config", lambda p: configs.append(p) or real_config(p))
    built = resolve("policy:cbf", SHIPPED)
    assert reads == ["model.safetensors"] and len(configs) == 1
    assert built.name == "egcbf+:cbf" and built.robot == "quadrotor" and built.checkpoint == SHIPPED
    assert built.weights_sha256 == ckpt_module.sha256(SHIPPED / "model.safetensors")
    assert built.env_overrides == dict(built.train_config.env_overrides)
    assert isinstance(built.controller, FilteredController) and built.controller.cbf is not None
    assert built.cbf is built.controller.cbf
    reads.clear()
    alone = resolve("policy:dcbf", SHIPPED, with_cbf=True)  # the CBF for a recording, from the same one read
    assert reads == ["model.safetensors"] and alone.cbf is not None and alone.controller.cbf is None
    assert resolve("policy", SHIPPED).cbf is None and resolve("nominal", with_cbf=True).cbf is None


def test_the_learned_controller_is_the_checkpoints_policy():
    built = resolve("egcbf+", SHIPPED, dtype=torch.float64)
    assert isinstance(built.controller, LearnedController) and built.filter == "none"
    reference, _ = ckpt_module.load_controller(SHIPPED, dtype=torch.float64)
    env = SwarmEnv(EnvConfig(num_agents=6, area_size=2.0, **built.env_overrides), dtype=torch.float64)
    state = env.reset(3)
    u, _ = built.controller(state, env.config)
    u_ref, _ = reference(state, env.config)
    assert torch.equal(u, u_ref)


@pytest.mark.parametrize(
    ("name", "expected"),
    [("egcbf+", True), ("egcbf+:dcbf", True), ("nominal", False), ("nominal:dcbf", {"messages"}),
     ("dcbf", {"messages"})],
)  # fmt: skip
def test_what_a_controller_perceives_is_answered_from_its_name(name, expected):
    got = reads_sensing(name)
    assert (set(got) if isinstance(got, frozenset) else got) == expected
    if name in ("nominal", "nominal:dcbf", "dcbf"):  # and agrees with the built controller's own declaration
        built = resolve(name).reads_sensing
        assert (set(built) if isinstance(built, frozenset) else built) == expected


def test_controllers_are_built_in_one_place():
    """Outside ``egcbf.control``, no module constructs a filtered controller, loads a checkpoint's controller or
    calls the hand-crafted registry: they ask :func:`egcbf.control.resolve.resolve`."""
    forbidden = {"FilteredController", "load_controller", "make_controller", "load_filtered_controller"}
    offenders = []
    for path in (REPO / "src" / "egcbf").rglob("*.py"):
        if path.parent.name == "control" or path.name == "checkpoint.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in forbidden:
                if not (path.name == "episodes.py" and node.func.id == "make_controller"):  # its factory argument
                    offenders.append(f"{path.relative_to(REPO)}:{node.lineno} {node.func.id}")
    assert not offenders, offenders
    for module in ("cli/eval.py", "cli/demo.py", "reproduce/workers.py", "study/driver.py", "robustness/plan.py"):
        text = (REPO / "src" / "egcbf" / module).read_text()
        assert "resolve" in text or "build_controller" in text, module
    assert resolve_module.resolve is resolve


def test_the_filters_are_classes_registered_by_their_kind():
    from egcbf.control.filters import FILTER_CLASSES, FILTERS, READS_SENSING, SafetyFilter, register_filter

    assert set(FILTER_CLASSES) == set(FILTERS[1:]) and set(READS_SENSING) == set(FILTERS[1:])
    for kind, cls in FILTER_CLASSES.items():
        assert issubclass(cls, SafetyFilter) and cls.kind == kind
        built = resolve(f"nominal:{kind}") if not cls.needs_cbf else resolve(f"policy:{kind}", SHIPPED)
        assert isinstance(built.controller.rows, cls)
        assert built.controller.config.settings() == cls.settings(built.controller.config)

    class Unnamed(SafetyFilter):
        kind = "mpc"

    with pytest.raises(ValueError, match="kind is one of"):
        register_filter(Unnamed)
