"""Scene layouts (where starts and goals are drawn) and the scene rotation of :class:`egcbf.env.EnvConfig`.

Layouts (``EnvConfig.scene``):

* ``"uniform"``: starts and goals uniform in the arena ``[0, l]^d`` (GCBF+'s and the paper's episodes);
* ``"crossing"``: starts uniform in the half ``x < l / 2`` of the arena, goals in the half ``x > l / 2``: every agent
  travels along ``+x`` (by ``l / 2`` on average), a training distribution with a preferred direction, for the
  rotated-world test of the paper's third claim (docs/equivariance.md).

Obstacle centres stay uniform in ``[0, l]^d`` in every layout.

Rotation (``EnvConfig.scene_yaw``, degrees): the sampled scene (start positions, goals, obstacle centres and the
agents' yaws) is rotated about the vertical axis through the arena's centre ``(l / 2, l / 2)``, counter-clockwise
seen from ``+z``; ``z`` is unchanged. It is an element of SE(2) (SE(2) x R in 3-D), so an equivariant controller's
episode from a rotated scene is the rotated episode (``tests/egcbf/test_scenes.py``), while a world-frame one may
behave differently. With a rotation that is not a multiple of 90 degrees, points can leave the square ``[0, l]^2``;
the arena has no walls, so nothing else changes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["SCENES", "cos_sin_degrees", "rotate_about_center", "scene_boxes", "wrap_angle"]

SCENES = ("uniform", "crossing")

Box = tuple[tuple[float, float], ...]


def scene_boxes(scene: str, area_size: float, dim: int) -> tuple[Box, Box] | None:
    """``(start box, goal box)``, each ``dim`` pairs ``(low, high)`` in metres (world frame), or ``None`` for
    ``"uniform"`` (both sets in ``[0, l]^dim``, drawn together as they always were)."""
    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; choose one of {SCENES}")
    if scene == "uniform":
        return None
    l = float(area_size)
    rest = ((0.0, l),) * (dim - 1)
    return ((0.0, l / 2), *rest), ((l / 2, l), *rest)


def rotate_about_center(points: Tensor, yaw_deg: float, area_size: float) -> Tensor:
    """``points`` ``(..., d)`` (world frame, ``d`` = 2 or 3) rotated by ``yaw_deg`` degrees about the vertical axis
    through ``(l / 2, l / 2)``; ``z`` unchanged. Exact for multiples of 90 degrees (no rounding of cos and sin)."""
    c, s = cos_sin_degrees(yaw_deg)
    h = float(area_size) / 2
    x, y = points[..., 0] - h, points[..., 1] - h
    out = points.clone()
    out[..., 0] = c * x - s * y + h
    out[..., 1] = s * x + c * y + h
    return out


def cos_sin_degrees(yaw_deg: float) -> tuple[float, float]:
    """``(cos, sin)`` of an angle in degrees, exact for multiples of 90 degrees."""
    quarter = float(yaw_deg) / 90.0
    if quarter == round(quarter):
        return ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))[round(quarter) % 4]
    a = math.radians(float(yaw_deg))
    return math.cos(a), math.sin(a)


def wrap_angle(angle: Tensor) -> Tensor:
    """``angle`` (radians) wrapped to ``[-pi, pi)``."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi
