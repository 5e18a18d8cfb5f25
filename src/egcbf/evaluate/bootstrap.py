"""Confidence intervals for learned controllers' metrics by a two-level bootstrap over training seeds and episodes.

A method's value in a cell is measured as ``runs``: one list per training seed of per-episode values (an evaluation
row's ``per_episode[key]``, :data:`egcbf.evaluate.episodes.PER_EPISODE_KEYS`). Its estimate is the mean over seeds of
each seed's mean over episodes. A resample draws the seeds with replacement, then, within each drawn seed, its episodes
with replacement, and takes the same mean: the interval (percentile, ``level``) covers both the training seeds' spread
and the episodes' noise. With one seed only the episodes are resampled, and the interval says nothing of how another
training seed would do (:attr:`Interval.seeds` tells).

:func:`difference_ci` bootstraps ``mean(a) - mean(b)`` with ``a`` and ``b`` resampled independently (different
training runs of different methods; the evaluation episodes are the same scenes, but each method's episodes are its
own outcomes).

Every function is deterministic given ``seed``; values are float64.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

__all__ = ["Interval", "difference_ci", "mean_ci"]


class Interval(NamedTuple):
    """``estimate`` with its ``level`` interval ``[low, high]``, from ``resamples`` resamples of ``seeds`` training
    seeds (``episodes``: the fewest episodes of any seed)."""

    estimate: float
    low: float
    high: float
    level: float
    resamples: int
    seeds: int
    episodes: int

    def excludes_zero(self) -> bool:
        """Whether the interval lies on one side of 0 (a difference whose sign the data settle)."""
        return self.low > 0 or self.high < 0

    def text(self, scale: float = 1.0, digits: int = 1) -> str:
        """``"+1.2 [-0.3, +2.8]"`` (values times ``scale``, e.g. 100 for rate points)."""
        e, lo, hi = (round(scale * v, digits) + 0.0 for v in (self.estimate, self.low, self.high))  # no "-0.00"
        return f"{e:+.{digits}f} [{lo:+.{digits}f}, {hi:+.{digits}f}]"


def _check_runs(runs: Sequence[Sequence[float]], name: str) -> list[np.ndarray]:
    if isinstance(runs, (str, bytes)) or not isinstance(runs, Sequence) or len(runs) == 0:
        raise ValueError(f"{name} must be a non-empty list (one per training seed) of per-episode value lists")
    out = []
    for k, run in enumerate(runs):
        arr = np.asarray(run, dtype=np.float64)
        if arr.ndim != 1 or arr.size == 0:
            raise ValueError(f"{name}[{k}] must be a non-empty list of per-episode values, got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}[{k}] holds NaN or inf")
        out.append(arr)
    return out


def _check_options(level: float, resamples: int) -> None:
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if not isinstance(resamples, int) or isinstance(resamples, bool) or resamples < 100:
        raise ValueError(f"resamples must be an integer >= 100, got {resamples!r}")


def _estimate(runs: list[np.ndarray]) -> float:
    return float(np.mean([r.mean() for r in runs]))


def _resampled_means(runs: list[np.ndarray], resamples: int, rng: np.random.Generator) -> np.ndarray:
    """``(resamples,)``: the two-level bootstrap distribution of the mean over seeds of the mean over episodes."""
    k = len(runs)
    seeds = rng.integers(0, k, size=(resamples, k)) if k > 1 else np.zeros((resamples, 1), dtype=np.int64)
    # each (resample, seed slot) draws the episodes of the seed it picked
    per_seed = np.empty((resamples, k), dtype=np.float64)
    for j, run in enumerate(runs):
        picked = seeds == j
        count = int(picked.sum())
        if count:
            idx = rng.integers(0, run.size, size=(count, run.size))
            per_seed[picked] = run[idx].mean(axis=1)
    return per_seed.mean(axis=1)


def _interval(estimate: float, dist: np.ndarray, level: float, runs: list[np.ndarray], resamples: int) -> Interval:
    lo, hi = np.quantile(dist, [(1 - level) / 2, (1 + level) / 2])
    # the percentile interval of a distribution always holds its estimate only up to rounding: clamp
    lo, hi = min(float(lo), estimate), max(float(hi), estimate)
    return Interval(estimate, lo, hi, level, resamples, len(runs), min(r.size for r in runs))


def mean_ci(
    runs: Sequence[Sequence[float]], *, level: float = 0.95, resamples: int = 10_000, seed: int = 0
) -> Interval:
    """The mean over training seeds of the mean over episodes of ``runs`` (one list of per-episode values per
    seed), with its two-level bootstrap interval."""
    arrays = _check_runs(runs, "runs")
    _check_options(level, resamples)
    rng = np.random.default_rng(seed)
    return _interval(_estimate(arrays), _resampled_means(arrays, resamples, rng), level, arrays, resamples)


def difference_ci(
    a: Sequence[Sequence[float]],
    b: Sequence[Sequence[float]],
    *,
    level: float = 0.95,
    resamples: int = 10_000,
    seed: int = 0,
) -> Interval:
    """``mean(a) - mean(b)`` (each as :func:`mean_ci`), with the interval of independently resampled ``a`` and ``b``;
    ``seeds`` and ``episodes`` of the result are the smaller of the two sides'."""
    ra, rb = _check_runs(a, "a"), _check_runs(b, "b")
    _check_options(level, resamples)
    rng = np.random.default_rng(seed)
    dist = _resampled_means(ra, resamples, rng) - _resampled_means(rb, resamples, rng)
    iv = _interval(_estimate(ra) - _estimate(rb), dist, level, ra, resamples)
    return iv._replace(seeds=min(len(ra), len(rb)), episodes=min(iv.episodes, min(r.size for r in rb)))
