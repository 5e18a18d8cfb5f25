"""The CBF contour figure: level sets of one agent's learned CBF ``h`` for a scene and for its transformed copy.

The paper's figure shows top-down views of the CBF "from the perspective of agent 1" for a graph ``G`` and for
``phi_g(G)``, ``g in SE(2) x R``: the learned ``h`` of one agent as a function of where that agent is placed in the
horizontal plane (its ``x, y`` varied over a grid; its height, attitude, velocity and body rates and the rest of
the scene unchanged). For an invariant CBF (EGCBF, EGCBF+) the two maps are the same map moved by ``g``; for an
ordinary GNN (GCBF, GCBF+, world-frame features) they differ wherever the rotation part of ``g`` matters.

* :func:`cbf_slice`: the map ``(X, Y, H)`` of one agent over a grid, for a scene or its transformed copy
  (``transform=g``: the scene is ``state.transform(g)`` and the grid is the original grid moved by ``g``, so
  ``H`` of the copy is comparable with the original point by point).
* :func:`cbf_contour_figure`: one row per method, three panels: contours in the original scene, contours in the
  transformed scene (in its own world coordinates), and ``|h(g . G) - h(G)|`` pulled back to the original grid.

Every placement is a separate environment of one batched graph (:func:`egcbf.env.graph.build_graph`), evaluated in
chunks; the LiDAR of the placed agent is recast for every placement (the other agents' scans do not depend on
where it is: the LiDAR sees only the static obstacles, so they are cast once).

    from egcbf.viz.contour import cbf_contour_figure
    diffs = cbf_contour_figure({"EGCBF+": Path("checkpoints/egcbf+"), "GCBF+": Path("checkpoints/gcbf+")},
                               Path("out/cbf_contours.png"))
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..env.config import EnvConfig
from ..env.graph import build_graph
from ..env.lidar import LidarScan
from ..env.swarm import SwarmEnv, SwarmState, cast_lidar
from ..nn import CBFNet
from ..robots.quadrotor import dynamics as dyn

__all__ = ["cbf_contour_figure", "cbf_slice", "load_cbf", "pick_agent", "transform_element"]

Extent = tuple[float, float, float, float]


def transform_element(
    theta: float, translation: Sequence[float] = (0.0, 0.0, 0.0), *, dtype=torch.float64, device=None
) -> Tensor:
    """The SE2xR element ``(cos theta, sin theta, tx, ty, tz)`` ``(5,)``: a rotation by ``theta`` (rad) about the
    world z axis followed by the translation ``(tx, ty, tz)`` (m), acting as ``p -> R_z(theta) p + t``."""
    t = [float(v) for v in translation]
    if len(t) != 3:
        raise ValueError(f"translation must have 3 components (tx, ty, tz), got {len(t)}")
    return torch.tensor([math.cos(theta), math.sin(theta), *t], dtype=dtype, device=device)


def load_cbf(path: str | Path, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float64):
    """The learned CBF of a checkpoint (or run) directory: ``(CBFNet in eval mode, TrainConfig)``.

    Needs only ``config.json`` and ``model.safetensors`` (the ``cbf.*`` weights).
    """
    from ..train.checkpoint import load_network

    return load_network(path, "cbf", device, dtype)


def _grid(extent: Extent, grid: int, dtype, device) -> tuple[Tensor, Tensor]:
    x0, x1, y0, y1 = (float(v) for v in extent)
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"extent must be (xmin, xmax, ymin, ymax) with xmin < xmax and ymin < ymax, got {extent}")
    xs = torch.linspace(x0, x1, grid, dtype=dtype, device=device)
    ys = torch.linspace(y0, y1, grid, dtype=dtype, device=device)
    return torch.meshgrid(xs, ys, indexing="xy")  # (grid, grid): X[i, j] = xs[j], Y[i, j] = ys[i]


def _placements(state: SwarmState, config: EnvConfig, agent: int, xy: Tensor, base: LidarScan):
    """``P = len(xy)`` copies of the one-environment ``state`` with agent ``agent`` moved to ``xy`` ``(P, 2)``
    (height unchanged), and their LiDAR scans (the moved agent's recast, the others' from ``base``)."""
    p = xy.shape[0]
    x = state.x.expand(p, -1, -1).clone()
    x[:, agent, 0:2] = xy
    obstacles = state.obstacles.expand(p)  # views: read only
    placed = SwarmState(x, state.goals.expand(p, -1, -1), obstacles, state.t, state.robot)
    sel = slice(agent, agent + 1)
    own = cast_lidar(config, x[:, sel, 0:3], placed.attitudes[:, sel, :, 0], obstacles)
    parts = {}
    for name in ("points", "valid", "distance"):
        t = getattr(base, name).expand(p, *getattr(base, name).shape[1:]).clone()
        t[:, sel] = getattr(own, name)
        parts[name] = t
    return placed, LidarScan(**parts)


@torch.no_grad()
def cbf_slice(
    cbf: CBFNet,
    state: SwarmState,
    env_config: EnvConfig,
    agent: int = 0,
    *,
    grid: int = 60,
    extent: Extent | None = None,
    transform: Tensor | None = None,
    chunk: int = 256,
) -> tuple[Tensor, Tensor, Tensor]:
    """The CBF value of agent ``agent`` as a function of its horizontal position.

    Agent ``agent`` is placed at every point of a ``grid x grid`` grid over ``extent`` (its ``x, y`` set there;
    its height, attitude, velocity, body rates, its goal and all other agents and obstacles unchanged), the graph of
    every placement is built from scratch (LiDAR recast) and ``h_agent`` is read from the network. Placements are
    evaluated as environments of one batched graph, ``chunk`` at a time.

    With ``transform = g`` (an SE2xR element ``(5,)``, :func:`transform_element`) the scene is
    ``state.transform(g)`` and the agent is placed at the grid points moved by ``g``: ``X, Y`` are then in the
    transformed scene's world coordinates (a rotated grid) and ``H[i, j]`` belongs to the same placement, seen
    through ``g``, as ``H[i, j]`` without ``transform``. For an SE2xR-invariant CBF the two ``H`` are equal up
    to rounding.

    Args:
        cbf: the CBF network (:class:`egcbf.nn.CBFNet`, e.g. from :func:`load_cbf`); the state is cast to its dtype
            and device.
        state: one environment (``B = 1``) of ``N`` agents, world frame, metres.
        env_config: the sensing settings (comm radius, LiDAR pattern and range) the CBF was trained with.
        agent: index of the agent whose ``h`` is mapped.
        grid: points per axis.
        extent: ``(xmin, xmax, ymin, ymax)`` of the grid in the *original* scene's world frame (m); default the
            arena ``[0, l]^2`` of ``env_config``.
        transform: an optional SE2xR element ``g`` ``(5,)`` (see above).
        chunk: placements per batched graph (memory: ``chunk * N`` agents).

    Returns:
        ``X, Y, H``, each ``(grid, grid)`` (``X[i, j]``, ``Y[i, j]``: world position of placement ``(i, j)`` in m,
        rows along ``y``, columns along ``x`` before ``g``; ``H``: ``h_agent`` there, in ``(-1, 1)``), on the
        CBF's device and dtype.
    """
    if state.num_envs != 1:
        raise ValueError(f"cbf_slice maps one scene: state must hold 1 environment, got {state.num_envs}")
    if not 0 <= agent < state.num_agents:
        raise ValueError(f"agent must be in [0, {state.num_agents}), got {agent}")
    if grid < 2 or chunk < 1:
        raise ValueError(f"grid must be >= 2 and chunk >= 1, got grid={grid}, chunk={chunk}")
    param = next(cbf.parameters())
    dtype, device = param.dtype, param.device
    state = state.to(device=device, dtype=dtype)
    if extent is None:
        extent = (0.0, env_config.area_size, 0.0, env_config.area_size)
    X, Y = _grid(extent, grid, dtype, device)
    xy = torch.stack((X.reshape(-1), Y.reshape(-1)), dim=-1)  # (P, 2)
    if transform is not None:
        g = transform.to(device=device, dtype=dtype)
        dyn.GROUP.check(g, "transform")
        if g.dim() != 1:
            raise ValueError(f"transform must be one SE2xR element (5,), got {tuple(g.shape)}")
        state = state.transform(g)
        pts = torch.cat((xy, torch.zeros_like(xy[:, :1])), dim=-1)
        xy = dyn.GROUP.transform(g.expand(pts.shape[0], -1), pts)[:, :2]
        X, Y = xy[:, 0].reshape(grid, grid), xy[:, 1].reshape(grid, grid)
    was_training = cbf.training
    cbf.eval()
    base = cast_lidar(env_config, state.positions, state.attitudes[..., :, 0], state.obstacles)
    n = state.num_agents
    out = []
    for k in range(0, xy.shape[0], chunk):
        placed, scan = _placements(state, env_config, agent, xy[k : k + chunk], base)
        h = cbf(build_graph(placed, env_config, lidar=scan))
        out.append(h.view(-1, n)[:, agent])
    cbf.train(was_training)
    return X, Y, torch.cat(out).reshape(grid, grid)


def pick_agent(state: SwarmState, config: EnvConfig) -> int:
    """The agent with the busiest neighbourhood in environment 0: the most other agents within the comm radius
    plus obstacles whose surface is within it (ties to the lower index). A deterministic, interesting default."""
    p = state.positions[0]
    r = config.comm_radius
    d = torch.cdist(p, p)
    score = (d < r).sum(-1) - 1
    if state.obstacles.num_obstacles:
        sd = state.obstacles.surface_distance(state.positions[:1])[0]  # (N, K)
        score = score + (sd < r).sum(-1)
    return int(torch.argmax(score))


# ------------------------------------------------------------------------------------------------- figure
def _to_np(t: Tensor) -> np.ndarray:
    return t.detach().cpu().double().numpy()


def _draw_scene(ax, state: SwarmState, agent: int, config: EnvConfig, corners: np.ndarray) -> None:
    """Arena outline (``corners`` ``(4, 2)``), obstacles cut at the agent's height, other agents, the agent (star),
    its comm-radius circle and its goal."""
    from matplotlib.patches import Circle, Polygon

    p = _to_np(state.positions[0])
    z = p[agent, 2]
    ax.add_patch(Polygon(corners, closed=True, fill=False, edgecolor="0.3", linestyle=":", linewidth=0.8))
    for c, r in zip(_to_np(state.obstacles.centers[0]), _to_np(state.obstacles.radii[0])):
        dz = abs(c[2] - z)
        if dz < r:  # horizontal section of the sphere at the agent's height
            ax.add_patch(Circle(c[:2], math.sqrt(r * r - dz * dz), facecolor="0.35", alpha=0.75, edgecolor="k"))
        ax.add_patch(Circle(c[:2], r, fill=False, edgecolor="0.35", linestyle="--", linewidth=0.6))
    others = np.arange(p.shape[0]) != agent
    ax.scatter(p[others, 0], p[others, 1], s=14, color="k", zorder=5, label="other agents")
    ax.scatter(*p[agent, :2], marker="*", s=90, color="gold", edgecolor="k", zorder=6, label=f"agent {agent}")
    ax.add_patch(Circle(p[agent, :2], config.comm_radius, fill=False, edgecolor="gold", linewidth=1.2, linestyle="--"))
    goal = _to_np(state.goals[0, agent])
    ax.scatter(*goal[:2], marker="x", s=40, color="tab:green", zorder=6, label="its goal")


def _contour_panel(ax, X, Y, H, state, agent, config, corners, title, vmax):
    levels = np.linspace(-vmax, vmax, 21)
    cs = ax.contourf(X, Y, H, levels=levels, cmap="RdBu", vmin=-vmax, vmax=vmax, extend="both")
    with warnings.catch_warnings():  # no zero crossing on the grid: nothing to draw
        warnings.simplefilter("ignore")
        ax.contour(X, Y, H, levels=[0.0], colors="k", linewidths=2.0)
    _draw_scene(ax, state, agent, config, corners)
    ax.set_xlim(X.min(), X.max())
    ax.set_ylim(Y.min(), Y.max())
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title, fontsize=9)
    return cs


def cbf_contour_figure(
    checkpoints: dict[str, Path],
    out_png: Path,
    *,
    seed: int = 0,
    num_agents: int = 8,
    area_size: float = 2.0,
    num_obstacles: int = 3,
    agent: int | None = None,
    theta: float = 2 * math.pi / 3,
    translation: Sequence[float] = (2.5, 0.5, 0.3),
    grid: int = 60,
    dtype: torch.dtype = torch.float64,
    dpi: int = 110,
) -> dict[str, float]:
    """Draw the CBF contour figure for several trained methods and return ``max |h(g . G) - h(G)|`` per method.

    One scene (``SwarmEnv(...).reset(seed)``: ``num_agents`` agents, ``num_obstacles`` spheres, arena
    ``[0, area_size]^3``) and one transform ``g`` = rotation by ``theta`` (rad) about z, then ``translation``
    (m). One row per entry of ``checkpoints`` (label -> checkpoint or run directory), three panels:

    1. ``h`` of agent ``agent`` over the arena (filled contours, ``h = 0`` in bold; red ``h < 0``), with the other
       agents, the obstacles cut at the agent's height (dashed: their full radius), the agent's position, comm
       radius and goal;
    2. the same for the transformed scene ``g . G``, drawn in its own world coordinates (the grid moved by ``g``);
    3. ``log10 |h(g . G) - h(G)|`` on the original grid (placements matched through ``g``), max in the title:
       rounding (``~1e-16`` in float64) for an invariant CBF, large for a non-invariant one.

    Each method uses its own training sensing settings (``env_overrides``). ``agent=None`` picks the agent with
    the busiest neighbourhood (:func:`pick_agent`). Written with the Agg backend at ``dpi``.

    Returns:
        ``{label: max |difference|}`` (floats).
    """
    from matplotlib.figure import Figure

    if not checkpoints:
        raise ValueError("cbf_contour_figure needs at least one checkpoint")
    g = transform_element(theta, translation, dtype=dtype)
    rows = len(checkpoints)
    fig = Figure(figsize=(14.0, 4.2 * rows), dpi=dpi, layout="constrained")
    axes = fig.subplots(rows, 3, squeeze=False)
    corners0 = np.array([[0, 0], [area_size, 0], [area_size, area_size], [0, area_size]], dtype=float)
    corners1 = corners0 @ _to_np(torch.stack((g[:2], torch.stack((-g[1], g[0]))))) + _to_np(g[2:4])
    diffs: dict[str, float] = {}
    for row, (label, path) in enumerate(checkpoints.items()):
        cbf, train_cfg = load_cbf(path, dtype=dtype)
        config = EnvConfig(
            num_agents=num_agents, area_size=area_size, num_obstacles=num_obstacles, **train_cfg.env_overrides
        )
        state = SwarmEnv(config, dtype=dtype).reset(seed)
        k = pick_agent(state, config) if agent is None else agent
        X, Y, H = cbf_slice(cbf, state, config, k, grid=grid)
        Xt, Yt, Ht = cbf_slice(cbf, state, config, k, grid=grid, transform=g)
        diff = (Ht - H).abs()
        diffs[label] = float(diff.max())
        moved = state.transform(g)
        ax0, ax1, ax2 = axes[row]
        # one colour scale per row, symmetric about h = 0 (red: h < 0), so that both scenes read alike
        vmax = max(float(H.abs().max()), float(Ht.abs().max()), 1e-6)
        cs = _contour_panel(
            ax0, *map(_to_np, (X, Y, H)), state, k, config, corners0, f"{label}: h of agent {k} in G", vmax
        )
        deg = math.degrees(theta)
        t = ", ".join(f"{v:g}" for v in translation)
        title = f"{label}: phi_g(G), g = rot {deg:.0f} deg, t = ({t}) m"
        _contour_panel(ax1, *map(_to_np, (Xt, Yt, Ht)), moved, k, config, corners1, title, vmax)
        fig.colorbar(cs, ax=[ax0, ax1], shrink=0.9, label="h (bold: h = 0)", format="%.2g", ticks=cs.levels[::5])
        logd = np.log10(np.maximum(_to_np(diff), 1e-17))
        im = ax2.imshow(
            logd,
            origin="lower",
            extent=(0, area_size, 0, area_size),
            vmin=-16,
            vmax=0,
            cmap="magma",
            interpolation="nearest",
        )
        ax2.set_aspect("equal")
        ax2.set_xlabel("x [m] (original grid)")
        ax2.set_ylabel("y [m]")
        ax2.set_title(f"{label}: |h(phi_g(G)) - h(G)|, max = {diffs[label]:.1e}", fontsize=9)
        fig.colorbar(im, ax=ax2, shrink=0.9, label="log10 |difference|")
    axes[0, 0].legend(loc="lower left", fontsize=6, framealpha=0.8)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=dpi)
    return diffs
