"""The paper's numbers and the names of the methods of ``egcbf reproduce``."""

from __future__ import annotations

from ..algo.config import LEARNED_METHODS
from ..control.names import filter_label, split_method
from ..marl import MARL_METHODS

__all__ = [
    "BASELINES",
    "DEFAULT_SIZES",
    "FILTERED",
    "LABELS",
    "LEARNED",
    "MARL",
    "METHODS",
    "PAPER_TABLE_I",
    "SCALE_SIZES",
    "PaperRow",
    "base_method",
    "method_filter",
]

#: the learned methods (``egcbf.algo.config.LEARNED_METHODS``: each one's group and reference controller)
LEARNED = tuple(LEARNED_METHODS)
BASELINES = ("dcbf", "ccbf", "nominal")
#: the safe multi-agent RL baselines (:mod:`egcbf.marl`, not in the paper): learned, one checkpoint each, no filter
MARL = MARL_METHODS
#: controllers behind a run-time safety filter (``egcbf eval --filter``, docs/safety_filters.md), ``METHOD:FILTER``
#: (:mod:`egcbf.control.names`), not in the paper: the learned policy behind the dCBF filter (EGCBF+, GCBF+), behind
#: its own learned CBF and behind the untrained prior CBF (the ablation that shows what the learned CBF adds), and
#: the nominal controller behind the dCBF filter (the ablation that shows what the learned policy adds)
FILTERED = ("egcbf+:dcbf", "gcbf+:dcbf", "egcbf+:cbf", "egcbf+:prior", "nominal:dcbf")
#: every controller the sweep evaluates (not only learned ones, unlike ``LEARNED_METHODS``), in the paper's row
#: order, then the nominal controller alone (not in the paper: what the learned residual starts from), then the
#: filtered controllers, then the MARL baselines
METHODS = ("gcbf", "gcbf+", "dcbf", "ccbf", "egcbf", "egcbf+", "nominal", *FILTERED, *MARL)
_BASE_LABELS = {
    "nominal": "nominal (no CBF)",
    "gcbf": "GCBF",
    "gcbf+": "GCBF+",
    "dcbf": "dCBF-QP",
    "ccbf": "cCBF-QP",
    "egcbf": "EGCBF",
    "egcbf+": "EGCBF+",
    "ippo-lag": "IPPO-Lagrangian",
}


def base_method(method: str) -> str:
    """The controller behind the filter of ``method`` (``egcbf+:dcbf`` -> ``egcbf+``), or ``method`` itself: a
    filtered learned method's checkpoints and training seeds are its base method's."""
    return split_method(method)[0]


def method_filter(method: str) -> str:
    """The run-time filter of ``method`` (``egcbf+:dcbf`` -> ``dcbf``; ``"none"`` for an unfiltered method)."""
    return split_method(method)[1]


def _label(method: str) -> str:
    base, filt = split_method(method)
    return _BASE_LABELS[method] if filt == "none" else filter_label(_BASE_LABELS[base].split(" (")[0], filt)


#: ``EGCBF+``, ``EGCBF+ + dCBF filter``, ``nominal + dCBF filter``, ...
LABELS = {m: _label(m) for m in METHODS}
#: Table I's swarm sizes (l = 4)
DEFAULT_SIZES = (8, 16, 64, 128, 256, 512)
#: the scalability study past the paper: N at the density of N = 512, l = 4 (8 agents per m^3)
SCALE_SIZES = (1024, 2048, 4096)

# The paper's Table I (l = 4): method -> N -> (safe %, reach %, success %, cost, cost min, cost max, reward);
# None where the paper prints '-' (its CBF-QPs stop at N = 16).
PaperRow = tuple[float, float, float, float, float, float, float]
PAPER_TABLE_I: dict[str, dict[int, PaperRow | None]] = {
    "nominal": {},
    "gcbf": {
        8: (100, 100, 100, 0, 0, 0, -315.1),
        16: (97.5, 100, 97.5, 0.33, 0, 2, -311.4),
        64: (87.7, 99.8, 87.5, 1.09, 0.31, 1.96, -315),
        128: (73.9, 99.1, 73.2, 2.47, 1.72, 4.12, -350.5),
        256: (52.1, 98.5, 51.1, 5.98, 4.66, 7.46, -409.3),
        512: (31.6, 96.8, 30, 11.07, 9.97, 13.4, -505.8),
    },
    "gcbf+": {
        8: (100, 100, 100, 0, 0, 0, -17.1),
        16: (100, 100, 100, 0, 0, 0, -17.5),
        64: (96.5, 100, 96.5, 0.23, 0, 1, -49.1),
        128: (93.6, 99.3, 92.9, 0.43, 0, 1.31, -104.2),
        256: (88.8, 98.7, 87.7, 0.72, 0.56, 0.92, -209.9),
        512: (77.8, 96.2, 74.5, 1.51, 1.2, 1.72, -484.2),
    },
    "dcbf": {
        8: (100, 100, 100, 0, 0, 0, -96.3),
        16: (100, 98.125, 98.13, 0, 0, 0, -182.8),
        64: None,
        128: None,
        256: None,
        512: None,
    },
    "ccbf": {
        8: (100, 100, 100, 0, 0, 0, -60.8),
        16: (100, 100, 100, 0, 0, 0, -120.5),
        64: None,
        128: None,
        256: None,
        512: None,
    },
    "egcbf": {
        8: (100, 91.2, 91.2, 0, 0, 0, -349.9),
        16: (100, 93.7, 93.7, 0, 0, 0, -338.5),
        64: (88.4, 94.2, 83.4, 1.256, 0.25, 2, -335.8),
        128: (74.1, 96.7, 71.7, 2.9, 2.04, 3.79, -358.1),
        256: (55.1, 97.5, 53.6, 5.42, 4.23, 7.36, -409.8),
        512: (33.1, 98.7, 31.7, 10.1, 7.03, 15.29, -487.3),
    },
    "egcbf+": {
        8: (100, 100, 100, 0, 0, 0, -9.3),
        16: (100, 100, 100, 0, 0, 0, -14.1),
        64: (98.8, 99.7, 98.5, 0.04, 0, 0.21, -34.7),
        128: (97.9, 99.5, 97, 0.12, 0, 0.23, -52.1),
        256: (94.2, 96.6, 91.1, 0.26, 0.06, 0.51, -97.8),
        512: (89.5, 92.1, 83.3, 0.51, 0.23, 0.73, -224.8),
    },
}
