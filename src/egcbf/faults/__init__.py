"""Real-world faults for evaluation: noisy sensing, lost and late messages, actuator errors, wind, non-cooperative
agents (docs/robustness.md).

    faults = parse_faults("default")                  # or "pos=0.02,loss=0.2", or a JSON file; FaultConfig(...)
    rows, _ = evaluate(make_controller, [512], faults=faults)
    egcbf eval --method egcbf+ --faults default ...   # the same from the command line

:mod:`~egcbf.faults.spec` (what each fault is, its units, the spec strings), :mod:`~egcbf.faults.process` (the
faults of a batch of episodes, step by step), :mod:`~egcbf.faults.sensing` (LiDAR and messages as the agents get
them), :mod:`~egcbf.faults.draws` (counter-based random draws, independent of batching).
"""

from .process import FaultProcess, noncooperative_mask
from .sensing import Sensing
from .spec import ALIASES, DEFAULT_FIELD, NONCOOP_MODES, FaultConfig, given_fields, parse_faults

__all__ = [
    "ALIASES",
    "DEFAULT_FIELD",
    "NONCOOP_MODES",
    "FaultConfig",
    "FaultProcess",
    "Sensing",
    "given_fields",
    "noncooperative_mask",
    "parse_faults",
]
