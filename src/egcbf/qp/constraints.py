"""The linear constraint rows every hand-crafted acceleration-level CBF-QP assembles: ``normal[c] . (a[i[c]] -
a[j[c]]) >= rhs[c]``, one row per agent pair or agent-obstacle pair (``j[c] = -1``), in units of acceleration.

The barriers that produce them are the robot's (the quadrotor's in :mod:`egcbf.robots.quadrotor.barriers`); the QP
cores (:mod:`egcbf.qp.sparse_qp`) only read them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Constraints"]


@dataclass
class Constraints:
    """Linear CBF constraints ``normal[c] . (a[i[c]] - a[j[c]]) >= rhs[c]`` (``j[c] = -1``: obstacle row).

    ``h`` is the barrier value of the row (``h0 = d^2 - D^2`` for ``hocbf``; ``h`` of Wang et al. for ``wang``);
    ``dist`` the centre distance (m), ``D`` its safety distance.
    """

    i: np.ndarray
    j: np.ndarray
    normal: np.ndarray
    rhs: np.ndarray
    h: np.ndarray
    dist: np.ndarray
    D: np.ndarray
    num_pairs: int = field(default=0)

    @staticmethod
    def empty() -> Constraints:
        z = np.zeros(0)
        zi = np.zeros(0, dtype=np.int64)
        return Constraints(zi, zi.copy(), np.zeros((0, 3)), z, z.copy(), z.copy(), z.copy(), 0)

    def __len__(self) -> int:
        return int(self.i.shape[0])

    @staticmethod
    def cat(parts: list[Constraints]) -> Constraints:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Constraints.empty()
        return Constraints(
            np.concatenate([p.i for p in parts]),
            np.concatenate([p.j for p in parts]),
            np.concatenate([p.normal for p in parts]),
            np.concatenate([p.rhs for p in parts]),
            np.concatenate([p.h for p in parts]),
            np.concatenate([p.dist for p in parts]),
            np.concatenate([p.D for p in parts]),
            sum(p.num_pairs for p in parts),
        )

    def subset(self, mask: np.ndarray) -> Constraints:
        """The rows selected by a boolean ``mask`` (pairs stay first)."""
        idx = np.nonzero(mask)[0]
        return Constraints(
            self.i[idx],
            self.j[idx],
            self.normal[idx],
            self.rhs[idx],
            self.h[idx],
            self.dist[idx],
            self.D[idx],
            int((idx < self.num_pairs).sum()),
        )

    def residual(self, a: np.ndarray) -> np.ndarray:
        """``lhs - rhs`` per row for accelerations ``a`` ``(M, 3)`` (>= 0 means satisfied)."""
        lhs = np.einsum("cd,cd->c", self.normal, a[self.i])
        pair = self.j >= 0
        lhs[pair] -= np.einsum("cd,cd->c", self.normal[pair], a[self.j[pair]])
        return lhs - self.rhs
