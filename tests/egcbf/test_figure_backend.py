"""Library figures never switch the user's matplotlib backend (a notebook keeps its own): they draw on
``matplotlib.figure.Figure`` objects with their own canvas."""

import matplotlib
import numpy as np

from egcbf.viz.render import render_comparison_gif, render_gif, render_topdown


def test_renders_keep_the_users_backend(tmp_path):
    before = matplotlib.get_backend()
    matplotlib.use("svg")  # any backend a user may have chosen; Agg is what the library must not force
    try:
        traj = np.linspace(0.5, 1.5, 4)[:, None, None] * np.ones((4, 2, 3))
        traj[:, 1] += 1.0
        coll = np.zeros((4, 2), dtype=bool)
        render_topdown(tmp_path / "a.png", traj, area_size=3.0)
        render_gif(tmp_path / "a.gif", traj, collided=coll, area_size=3.0, max_frames=3)
        render_comparison_gif(tmp_path / "b.gif", {"x": (traj, coll)}, area_size=3.0, max_frames=3)
        assert matplotlib.get_backend() == "svg"
        assert (tmp_path / "a.png").read_bytes()[:4] == b"\x89PNG"
        assert (tmp_path / "a.gif").read_bytes()[:3] == b"GIF"
    finally:
        matplotlib.use(before)
