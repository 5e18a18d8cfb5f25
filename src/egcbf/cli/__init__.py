"""Command line: ``egcbf eval`` (evaluate a controller over swarm sizes), ``egcbf train`` (learn a graph CBF and
policy), ``egcbf demo`` (the main job), ``egcbf reproduce`` (Table I and the scalability study), ``egcbf study``
(the equivariance study), ``egcbf robustness`` (every controller under real-world faults), ``egcbf certify``
(the learned CBFs measured as certificates), ``egcbf average`` (weight
averaging of two checkpoints) and ``egcbf export`` (one agent's controller as a TorchScript or ONNX file), one
module per command; :mod:`~egcbf.cli.root` holds the command group and :func:`main`, :mod:`~egcbf.cli.checks` the
input checks and :mod:`~egcbf.cli.choices` the fixed choices.

    egcbf eval --controller ccbf --num-agents 8,16,64 --area 4 --obstacles 0 --episodes 50 --seed 0 --out runs/ccbf
    egcbf train --algo egcbf+ --steps 300 --out runs/egcbf+          # CPU recipe; --preset paper --device cuda
    egcbf eval --checkpoint runs/egcbf+ --num-agents 8,16,64 --out runs/egcbf+/eval

Options with a fixed set of values take enums (:mod:`egcbf.cli.choices`): ``--help`` lists the values. A user
error (a bad flag value, an unusable file) ends a command with one ``Error: ...`` line naming the flag or file and
exit code 2 (:mod:`egcbf.cli.checks`); ``EGCBF_DEBUG=1`` shows the traceback instead. Every input is
checked before any work starts, and ``eval`` writes each swarm size's results as soon as it is finished.
"""

from . import average, certify, demo, eval, export, reproduce, robustness, study, train  # noqa: F401  (each registers its command on app, in this order)
from .root import app, main

__all__ = ["app", "main"]
