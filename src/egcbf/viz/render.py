"""Rendering of swarm episodes: a 3-D animation (GIF) and a top-down still (PNG).

Inputs are plain arrays (numpy or torch, CPU or GPU) so that any trajectory can be drawn:

    trajectory   (T, N, 3)  agent positions over time (world frame, metres)
    goals        (N, 3)     goal positions
    centers      (K, 3)     sphere obstacle centres,  radii (K,)
    boxes        (K, 4)     optional: planar rectangle obstacles' half sides and orientation (cos, sin)
    collided     (T, N)     optional collision mask (agents drawn red while colliding)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["render_comparison_gif", "render_gif", "render_topdown"]


def _np(a) -> np.ndarray | None:
    if a is None:
        return None
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=float)


def _lift(a: np.ndarray | None) -> np.ndarray | None:
    """Planar points ``(..., 2)`` at height 0, ``(..., 3)``; 3-D points unchanged."""
    if a is None or a.shape[-1] != 2:
        return a
    return np.concatenate((a, np.zeros((*a.shape[:-1], 1))), -1)


def _validate(trajectory, goals, centers, radii, collided):
    """Arrays of a 3-D or planar episode (planar points drawn at height 0)."""
    traj = _np(trajectory)
    if traj is None or traj.ndim != 3 or traj.shape[-1] not in (2, 3):
        raise ValueError(f"trajectory must be (T, N, 3) or (T, N, 2), got {None if traj is None else traj.shape}")
    d = traj.shape[-1]
    goals = _np(goals)
    if goals is not None and goals.shape != traj.shape[1:]:
        raise ValueError(f"goals must be (N, {d}) = {traj.shape[1:]}, got {goals.shape}")
    traj, goals = _lift(traj), _lift(goals)
    centers = np.zeros((0, 3)) if centers is None else _lift(_np(centers).reshape(-1, d))
    radii = np.zeros((0,)) if radii is None else _np(radii).reshape(-1)
    if centers.shape[0] != radii.shape[0]:
        raise ValueError(f"{centers.shape[0]} obstacle centres but {radii.shape[0]} radii")
    coll = None if collided is None else _np(collided).astype(bool)
    if coll is not None and coll.shape != traj.shape[:2]:
        raise ValueError(f"collided must be (T, N) = {traj.shape[:2]}, got {coll.shape}")
    if not np.isfinite(traj).all():
        raise ValueError("trajectory contains NaN or inf")
    return traj, goals, centers, radii, coll


def _corners(c: np.ndarray, box: np.ndarray) -> np.ndarray:
    """The four corners ``(4, 2)`` of a rectangle with centre ``c`` and ``box = (half sides, cos, sin)``."""
    a, b, co, si = box
    local = np.array([[a, b], [-a, b], [-a, -b], [a, -b]])
    return c[:2] + local @ np.array([[co, si], [-si, co]])


def _obstacles_2d(ax, centers, radii, boxes, **kw) -> None:
    """Grey discs, or the rectangles of ``boxes``, in the x-y plane."""
    from matplotlib.patches import Circle, Polygon

    for k, (c, r) in enumerate(zip(centers, radii)):
        if boxes is None:
            ax.add_patch(Circle(c[:2], r, color="0.6", alpha=0.6, **kw))
        else:
            ax.add_patch(Polygon(_corners(c, boxes[k]), closed=True, color="0.6", alpha=0.6, **kw))


def _boxes(boxes, centers: np.ndarray) -> np.ndarray | None:
    b = _np(boxes)
    if b is None or b.size == 0:
        return None
    b = b.reshape(-1, 4)
    if b.shape[0] != centers.shape[0]:
        raise ValueError(f"{centers.shape[0]} obstacle centres but {b.shape[0]} boxes")
    return b


def _sphere(ax, c, r, **kw):
    u, v = np.mgrid[0 : 2 * np.pi : 16j, 0 : np.pi : 9j]
    ax.plot_surface(c[0] + r * np.cos(u) * np.sin(v), c[1] + r * np.sin(u) * np.sin(v), c[2] + r * np.cos(v), **kw)


def render_gif(
    path: str | Path,
    trajectory,
    goals=None,
    centers=None,
    radii=None,
    collided=None,
    *,
    boxes=None,
    area_size: float | None = None,
    fps: int = 15,
    max_frames: int = 90,
    title: str = "",
    trail: int = 12,
) -> Path:
    """Write a 3-D animation of the episode to ``path`` (GIF) and return the path.

    At most ``max_frames`` frames are drawn (time steps are sub-sampled evenly); each agent leaves a short
    trail; colliding agents are red; goals are green crosses; obstacles grey spheres.
    """
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    traj, goals, centers, radii, coll = _validate(trajectory, goals, centers, radii, collided)
    rects = _boxes(boxes, centers)
    T, N, _ = traj.shape
    frames = np.unique(np.linspace(0, T - 1, min(T, max_frames)).round().astype(int))
    lo = 0.0 if area_size is not None else float(traj.min())
    hi = float(area_size) if area_size is not None else float(traj.max())
    fig = Figure(figsize=(5, 5), dpi=80)
    FigureCanvasAgg(fig)  # frames are grabbed from an Agg canvas, whatever the user's pyplot backend
    ax = fig.add_subplot(projection="3d")

    def draw(k):
        t = frames[k]
        ax.cla()
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_zlim(lo, hi)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.set_title(f"{title}  t = {t}".strip())
        for j, (c, r) in enumerate(zip(centers, radii)):
            if rects is None:
                _sphere(ax, c, r, color="0.5", alpha=0.35, linewidth=0)
            else:  # a planar rectangle: its outline at height 0
                xy = _corners(c, rects[j])
                ax.plot(*np.vstack((xy, xy[:1])).T, np.zeros(5), color="0.4")
        if goals is not None:
            ax.scatter(*goals.T, marker="x", color="tab:green", s=12, depthshade=False)
        t0 = max(0, t - trail)
        if N <= 256:
            for i in range(N):
                ax.plot(*traj[t0 : t + 1, i].T, color="tab:blue", alpha=0.35, linewidth=0.8)
        colors = np.where(coll[t], "tab:red", "tab:blue") if coll is not None else "tab:blue"
        ax.scatter(*traj[t].T, c=colors, s=10, depthshade=False)
        return ()

    anim = FuncAnimation(fig, draw, frames=len(frames), blit=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    anim.save(path, writer=PillowWriter(fps=fps))
    return path


def render_topdown(
    path: str | Path,
    trajectory,
    goals=None,
    centers=None,
    radii=None,
    collided=None,
    *,
    boxes=None,
    area_size: float | None = None,
    title: str = "",
) -> Path:
    """Write a top-down (x-y) still of the whole episode: paths, start (circle), end (dot), goals (cross),
    obstacles (grey discs of their radius, or rectangles), collision points (red)."""
    from matplotlib.figure import Figure

    traj, goals, centers, radii, coll = _validate(trajectory, goals, centers, radii, collided)
    fig = Figure(figsize=(5.5, 5.5), dpi=100)
    ax = fig.subplots()
    _obstacles_2d(ax, centers, radii, _boxes(boxes, centers))
    ax.plot(traj[:, :, 0], traj[:, :, 1], color="tab:blue", alpha=0.4, linewidth=0.8)
    ax.scatter(traj[0, :, 0], traj[0, :, 1], facecolors="none", edgecolors="tab:blue", s=14, label="start")
    ax.scatter(traj[-1, :, 0], traj[-1, :, 1], color="tab:blue", s=8, label="end")
    if goals is not None:
        ax.scatter(goals[:, 0], goals[:, 1], marker="x", color="tab:green", s=18, label="goal")
    if coll is not None and coll.any():
        t, i = np.nonzero(coll)
        ax.scatter(traj[t, i, 0], traj[t, i, 1], color="tab:red", s=10, label="collision")
    if area_size is not None:
        ax.set_xlim(0, area_size)
        ax.set_ylim(0, area_size)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=7)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    return path


def render_comparison_gif(
    path: str | Path,
    panels: dict,
    goals=None,
    centers=None,
    radii=None,
    *,
    boxes=None,
    area_size: float | None = None,
    fps: int = 12,
    max_frames: int = 80,
    trail: int = 16,
    title: str = "",
) -> Path:
    """Write a top-down (x-y) animation of several controllers on the same episode, one panel each, to ``path``.

    ``panels`` maps a label to ``(trajectory (T, N, 3), collided (T, N))`` of one controller (the same starts,
    goals and obstacles for all, e.g. the same evaluation seed). Each agent leaves a short trail; an agent is drawn
    red while it collides and keeps a red ring once it has collided; each panel's title counts the agents that have
    collided so far, so a controller that avoids stays blue while one that does not turns red. At most
    ``max_frames`` frames (time steps sub-sampled evenly, the last step always shown). Returns ``path``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from PIL import Image

    if not panels:
        raise ValueError("render_comparison_gif needs at least one panel")
    data = {}
    for label, (trajectory, collided) in panels.items():
        traj, g, c, r, coll = _validate(trajectory, goals, centers, radii, collided)
        if coll is None:
            raise ValueError(f"panel {label!r}: collided is required")
        data[label] = (traj, coll)
    shapes = {traj.shape for traj, _ in data.values()}
    if len(shapes) != 1:
        raise ValueError(f"every panel needs the same (T, N, 3) trajectory shape, got {sorted(shapes)}")
    T, N, _ = shapes.pop()
    frames = np.unique(np.linspace(0, T - 1, min(T, max_frames)).round().astype(int))
    lo = 0.0 if area_size is not None else min(float(t[..., :2].min()) for t, _ in data.values())
    hi = float(area_size) if area_size is not None else max(float(t[..., :2].max()) for t, _ in data.values())
    cols = min(len(data), 2 if len(data) == 4 else 3)
    rows = -(-len(data) // cols)
    fig = Figure(figsize=(3.6 * cols, 3.8 * rows + (0.3 if title else 0)), dpi=90)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    artists = []
    for ax, (label, (traj, coll)) in zip(axes, data.items()):
        _obstacles_2d(ax, c, r, _boxes(boxes, c))
        if g is not None:
            ax.scatter(g[:, 0], g[:, 1], marker="x", color="tab:green", s=10, lw=0.8)
        lines = LineCollection([], colors="tab:blue", alpha=0.35, linewidths=0.7)
        ax.add_collection(lines)
        dots = ax.scatter(traj[0, :, 0], traj[0, :, 1], s=9, color="tab:blue", zorder=3)
        rings = ax.scatter([], [], s=45, facecolors="none", edgecolors="red", linewidths=1.2, zorder=4)
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        artists.append((ax, label, traj, np.logical_or.accumulate(coll, axis=0), coll, lines, dots, rings))
    for ax in axes[len(data) :]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    images = []
    for t in frames:
        for ax, label, traj, ever, coll, lines, dots, rings in artists:
            t0 = max(0, t - trail)
            lines.set_segments([traj[t0 : t + 1, i, :2] for i in range(N)])
            dots.set_offsets(traj[t, :, :2])
            dots.set_color(np.where(coll[t], "red", "tab:blue"))
            rings.set_offsets(traj[t, ever[t], :2] if ever[t].any() else np.zeros((0, 2)))
            ax.set_title(f"{label}: {int(ever[t].sum())} of {N} collided", fontsize=9)
        fig.canvas.draw()
        frame = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())).convert("RGB")
        images.append(frame.quantize(colors=255, method=Image.Quantize.FASTOCTREE))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    durations = [round(1000 / fps)] * (len(images) - 1) + [1500]  # hold the last frame
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=durations, loop=0)
    return path
