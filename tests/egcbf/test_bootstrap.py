"""egcbf.evaluate.bootstrap: the two-level (seeds, then episodes) bootstrap of a method's mean and of a difference."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.evaluate.bootstrap import Interval, difference_ci, mean_ci

values = st.floats(0.0, 1.0, allow_nan=False)
runs_st = st.lists(st.lists(values, min_size=1, max_size=12), min_size=1, max_size=4)


@given(runs=runs_st, shift=st.floats(-3, 3), seed=st.integers(0, 2**16))
@settings(max_examples=40, deadline=None)
def test_mean_ci_is_the_mean_of_means_and_shifts_with_the_data(runs, shift, seed):
    """The estimate is the mean over seeds of each seed's mean; the interval holds it, is reproducible from its
    seed, and moves with a shift of every value (float64, 1e-12)."""
    iv = mean_ci(runs, resamples=500, seed=seed)
    assert iv.estimate == pytest.approx(np.mean([np.mean(r) for r in runs]), abs=1e-12)
    assert iv.low <= iv.estimate <= iv.high
    assert mean_ci(runs, resamples=500, seed=seed) == iv
    moved = mean_ci([[v + shift for v in r] for r in runs], resamples=500, seed=seed)
    for a, b in ((moved.estimate, iv.estimate), (moved.low, iv.low), (moved.high, iv.high)):
        assert a == pytest.approx(b + shift, abs=1e-12)
    assert (iv.seeds, iv.episodes) == (len(runs), min(len(r) for r in runs))


@given(runs_a=runs_st, runs_b=runs_st, seed=st.integers(0, 2**16))
@settings(max_examples=30, deadline=None)
def test_difference_ci_estimate_is_the_difference_and_holds_it(runs_a, runs_b, seed):
    iv = difference_ci(runs_a, runs_b, resamples=500, seed=seed)
    ea, eb = mean_ci(runs_a, resamples=500).estimate, mean_ci(runs_b, resamples=500).estimate
    assert iv.estimate == pytest.approx(ea - eb, abs=1e-12)
    assert iv.low <= iv.estimate <= iv.high
    back = difference_ci(runs_b, runs_a, resamples=500, seed=seed)
    assert back.estimate == pytest.approx(-iv.estimate, abs=1e-12)


def test_constant_data_give_a_point_and_identical_methods_a_difference_around_zero():
    iv = mean_ci([[0.9] * 20, [0.9] * 20], resamples=1000)
    assert iv.low == iv.high == iv.estimate == pytest.approx(0.9)
    rng = np.random.default_rng(0)
    same = [list(rng.uniform(0.8, 1.0, 50)) for _ in range(3)]
    d = difference_ci(same, same, resamples=2000)
    assert d.estimate == 0.0 and d.low < 0 < d.high and not d.excludes_zero()


def test_a_clear_difference_excludes_zero_and_prints_in_points():
    rng = np.random.default_rng(1)
    a = [list(rng.normal(0.99, 0.005, 50)) for _ in range(3)]
    b = [list(rng.normal(0.92, 0.02, 50)) for _ in range(3)]
    d = difference_ci(a, b)
    assert d.excludes_zero() and d.low > 0.05
    assert d.text(100).startswith("+7.") and "[" in d.text(100)


def test_seed_spread_widens_the_interval():
    """Three seeds that disagree give a wider interval than three that agree with the same episode noise: the
    bootstrap resamples seeds, not only episodes."""
    rng = np.random.default_rng(2)
    noise = [rng.normal(0, 0.01, 50) for _ in range(3)]
    agree = [list(0.9 + n) for n in noise]
    disagree = [list(c + n) for c, n in zip((0.8, 0.9, 1.0), noise)]
    w_agree = mean_ci(agree).high - mean_ci(agree).low
    w_disagree = mean_ci(disagree).high - mean_ci(disagree).low
    assert w_disagree > 5 * w_agree


def test_coverage_of_the_mean_is_near_its_level():
    """Over 200 data sets of 40 normal episodes (one seed), the 90 % interval covers the true mean in 80-97 % of them
    (the percentile bootstrap is slightly narrow for small samples)."""
    rng = np.random.default_rng(3)
    hits = sum(
        (lambda iv: iv.low <= 0.5 <= iv.high)(
            mean_ci([list(rng.normal(0.5, 0.1, 40))], level=0.9, resamples=400, seed=k)
        )
        for k in range(200)
    )
    assert 160 <= hits <= 194


@pytest.mark.parametrize(
    "bad, message",
    [
        ([], "non-empty list"),
        ("0.9", "non-empty list"),
        ([[]], r"runs\[0\] must be a non-empty list"),
        ([[0.5, float("nan")]], "NaN or inf"),
        ([[[0.5]]], r"runs\[0\] must be a non-empty list of per-episode values"),
    ],
)
def test_bad_runs_are_named(bad, message):
    with pytest.raises(ValueError, match=message):
        mean_ci(bad)


def test_bad_options_are_named():
    with pytest.raises(ValueError, match="level must be in"):
        mean_ci([[0.5]], level=95)
    with pytest.raises(ValueError, match="resamples must be an integer >= 100"):
        mean_ci([[0.5]], resamples=10)
    assert isinstance(mean_ci([[0.5, 0.6]]), Interval)


def test_text_never_writes_a_negative_zero():
    iv = Interval(-4e-7, -0.0049, 0.0053, 0.95, 2000, 1, 20)
    assert iv.text(100, 2) == "+0.00 [-0.49, +0.53]"
    assert Interval(-0.012, -0.02, -0.001, 0.95, 2000, 1, 20).text(100, 1) == "-1.2 [-2.0, -0.1]"
