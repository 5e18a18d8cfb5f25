"""Evaluation: closed-loop episodes of any controller on batched swarms (:mod:`~egcbf.evaluate.episodes`), the
per-episode metrics (:mod:`~egcbf.evaluate.metrics`), and intervals over training seeds and episodes
(:mod:`~egcbf.evaluate.bootstrap`)."""
