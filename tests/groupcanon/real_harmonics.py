"""The real spherical harmonics that docs/escnn.md states escnn's SO(3) basis in, written out from their formula (no
library's convention assumed), and the representation they define.

``real_harmonics(l, x)`` is ``(Y_{l,-l}(x), ..., Y_{l,l}(x))`` at the directions ``x`` ``(P, 3)``: ``Y_{l,0} = N_l0
P_l^0(cos theta)``, ``Y_{l,m} = sqrt(2) N_lm P_l^m(cos theta) cos(m phi)`` for ``m > 0`` and ``sqrt(2) N_l|m|
P_l^|m|(cos theta) sin(|m| phi)`` for ``m < 0``, with ``N_lm = sqrt((2l + 1) / (4 pi) (l - m)! / (l + m)!)`` and
``P_l^m`` the associated Legendre function **without** the Condon-Shortley phase ``(-1)^m``. ``harmonic_matrix(l, R)``
is the matrix ``S_l(R)`` with ``y_l(R x) = S_l(R) y_l(x)`` for every ``x``, fitted on random directions (exact to
~1e-13 in float64: ``y_l`` spans its space).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import lpmv

__all__ = ["E3NN_AXES", "YZX", "harmonic_matrix", "real_harmonics"]

#: escnn's degree-1 basis: ``S_1(R) = YZX R YZX^T`` (rows: the y, z, x axes)
YZX = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
#: e3nn's axes: its degree-l harmonics are these of ``(z, x, y)``, so its ``D^l(R) = S_l(Pi) S_l(R) S_l(Pi)^T``
E3NN_AXES = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def real_harmonics(l: int, x: np.ndarray) -> np.ndarray:
    """``(P, 2l + 1)``: the degree-``l`` real spherical harmonics at the directions of ``x`` ``(P, 3)`` (module doc)."""
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    cos_theta, phi = x[:, 2], np.arctan2(x[:, 1], x[:, 0])
    columns = []
    for m in range(-l, l + 1):
        a = abs(m)
        norm = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - a) / math.factorial(l + a))
        legendre = (-1) ** a * lpmv(a, l, cos_theta)  # scipy's lpmv carries the Condon-Shortley phase: removed
        if m == 0:
            columns.append(norm * legendre)
        else:
            trig = np.sin(a * phi) if m < 0 else np.cos(a * phi)
            columns.append(math.sqrt(2.0) * norm * legendre * trig)
    return np.stack(columns, -1)


def harmonic_matrix(l: int, rotation: np.ndarray, num_points: int = 400, seed: int = 0) -> np.ndarray:
    """``S_l(R)`` ``(2l + 1, 2l + 1)``: how the degree-``l`` harmonics transform, ``y_l(R x) = S_l(R) y_l(x)``."""
    x = np.random.default_rng(seed).normal(size=(num_points, 3))
    y, y_rotated = real_harmonics(l, x), real_harmonics(l, x @ rotation.T)
    return np.linalg.lstsq(y, y_rotated, rcond=None)[0].T
