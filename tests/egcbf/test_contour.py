"""The CBF contour figure: the slice of an invariant CBF is the same map moved by g; a GCBF's is not."""

import math

import pytest
import torch

from egcbf.algo.config import TrainConfig
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.env.obstacles import Obstacles
from egcbf.env.swarm import SwarmState
from egcbf.nn import CBFNet, ModelConfig
from egcbf.train.checkpoint import find_checkpoint
from egcbf.train.loop import train
from egcbf.viz.contour import cbf_contour_figure, cbf_slice, load_cbf, transform_element

F64 = torch.float64
CFG = EnvConfig(num_agents=4, area_size=1.5, num_obstacles=2, n_rays=8, lidar_max_hits=4)


def _net(group: str) -> CBFNet:
    torch.manual_seed(0)
    return CBFNet(ModelConfig(group=group, hidden=16, heads=4, head_hidden=16)).double()


@pytest.fixture(scope="module")
def scene():
    return SwarmEnv(CFG, dtype=F64).reset(5)


@pytest.mark.parametrize("theta, t", [(1.0, (0.3, -0.2, 0.1)), (-2.5, (1.0, 2.0, -0.4)), (math.pi / 2, (0, 0, 0))])
def test_invariant_cbf_gives_the_same_slice_in_the_transformed_scene(scene, theta, t):
    g = transform_element(theta, t)
    net = _net("se2xr")
    X, Y, H = cbf_slice(net, scene, CFG, 1, grid=12, chunk=50)
    Xt, Yt, Ht = cbf_slice(net, scene, CFG, 1, grid=12, transform=g)
    assert H.shape == Ht.shape == X.shape == Xt.shape == (12, 12) and H.dtype == F64
    assert (Ht - H).abs().max() <= 1e-9
    assert H.max() - H.min() > 1e-4  # the map is not flat: the test would catch a broken placement
    # the transformed grid is the original grid moved by g
    c, s = math.cos(theta), math.sin(theta)
    assert torch.allclose(Xt, c * X - s * Y + t[0], atol=1e-12) and torch.allclose(Yt, s * X + c * Y + t[1], atol=1e-12)


def test_gcbf_slice_changes_under_rotation_but_not_translation(scene):
    net = _net("trivial")
    _, _, H = cbf_slice(net, scene, CFG, 1, grid=12)
    _, _, Hr = cbf_slice(net, scene, CFG, 1, grid=12, transform=transform_element(1.0, (0.3, -0.2, 0.1)))
    _, _, Ht = cbf_slice(net, scene, CFG, 1, grid=12, transform=transform_element(0.0, (0.3, -0.2, 0.1)))
    assert (Hr - H).abs().max() > 1e-4
    assert (Ht - H).abs().max() <= 1e-9  # world-frame features, but no absolute positions


def test_slice_equals_building_every_placement_from_scratch(scene):
    """The batched placements with the moved agent's LiDAR recast equal build_graph(lidar=None) per placement."""
    net = _net("se2xr")
    X, Y, H = cbf_slice(net, scene, CFG, 2, grid=4, extent=(-0.2, 1.7, 0.1, 1.4), chunk=5)
    p = X.numel()
    x = scene.x.expand(p, -1, -1).clone()
    x[:, 2, 0:2] = torch.stack((X.reshape(-1), Y.reshape(-1)), dim=-1)
    obs = Obstacles(scene.obstacles.centers.expand(p, -1, -1), scene.obstacles.radii.expand(p, -1))
    placed = SwarmState(x, scene.goals.expand(p, -1, -1), obs)
    with torch.no_grad():
        ref = net(build_graph(placed, CFG)).view(p, -1)[:, 2]
    assert torch.allclose(ref.reshape(4, 4), H, atol=1e-12, rtol=0)
    assert X[0, 0] == -0.2 and X[0, -1] == 1.7 and Y[-1, 0] == 1.4


def test_slice_rejects_bad_input(scene):
    net = _net("se2xr")
    with pytest.raises(ValueError, match="agent"):
        cbf_slice(net, scene, CFG, 9, grid=4)
    with pytest.raises(ValueError, match="extent"):
        cbf_slice(net, scene, CFG, 0, grid=4, extent=(1.0, 0.0, 0.0, 1.0))


@pytest.fixture(scope="module")
def tiny_checkpoints(tmp_path_factory):
    out = {}
    for algo in ("egcbf+", "gcbf+"):
        run = tmp_path_factory.mktemp(algo.replace("+", "p"))
        train(TrainConfig.preset(algo, "tiny", steps=1), run, progress=False, log=lambda s: None)
        out[algo] = find_checkpoint(run)
    return out


def test_contour_figure_from_checkpoints(tiny_checkpoints, tmp_path):
    cbf, cfg = load_cbf(tiny_checkpoints["egcbf+"])
    assert cfg.algo == "egcbf+" and next(cbf.parameters()).dtype == F64 and not cbf.training
    png = tmp_path / "fig" / "contours.png"
    diffs = cbf_contour_figure(
        {"EGCBF+": tiny_checkpoints["egcbf+"], "GCBF+": tiny_checkpoints["gcbf+"]},
        png,
        num_agents=4,
        area_size=1.5,
        num_obstacles=2,
        grid=12,
        dpi=50,
    )
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size < 400_000
    assert set(diffs) == {"EGCBF+", "GCBF+"}
    assert diffs["EGCBF+"] <= 1e-9 < 1e-6 < diffs["GCBF+"]
