"""Statistics over seeds, checked against values worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drago.eval.stats import Summary, aggregate, iqm, stratified_bootstrap_ci, summarize


def test_iqm_drops_a_quarter_from_each_end():
    # 8 values: int(0.25 * 8) = 2 dropped from each end, leaving 3, 4, 5, 6.
    assert iqm(np.arange(1, 9)) == pytest.approx(4.5)
    # The outliers 10 and 100 and the two zeros are trimmed; the middle is all ones.
    assert iqm([0, 0, 1, 1, 1, 1, 10, 100]) == pytest.approx(1.0)
    # Unsorted input gives the same answer as sorted.
    assert iqm([100, 1, 0, 10, 1, 0, 1, 1]) == pytest.approx(1.0)


def test_iqm_of_fewer_than_four_values_is_the_mean():
    assert iqm([1.0, 2.0, 9.0]) == pytest.approx(4.0)


def test_iqm_along_an_axis():
    a = np.array([[1, 2, 3, 4, 5, 6, 7, 8], [0, 0, 1, 1, 1, 1, 10, 100]], dtype=float)
    np.testing.assert_allclose(iqm(a, axis=1), [4.5, 1.0])
    # 5 rows: int(1.25) = 1 dropped from each end of every column.
    b = np.array([[0.0, 10.0], [1.0, 20.0], [2.0, 30.0], [3.0, 40.0], [100.0, 50.0]])
    np.testing.assert_allclose(iqm(b, axis=0), [2.0, 30.0])
    # axis=None pools everything: 10 values, 2 dropped from each end.
    assert iqm(b) == pytest.approx(np.mean([2.0, 3.0, 10.0, 20.0, 30.0, 40.0]))


def test_iqm_propagates_nan_and_rejects_empty():
    assert math.isnan(iqm([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, np.nan]))
    with pytest.raises(ValueError):
        iqm([])


def test_summarize_three_values_by_hand():
    s = summarize([1.0, 2.0, 4.0])
    assert s.n == 3
    assert s.mean == pytest.approx(7.0 / 3.0)
    # Squared deviations from 7/3: 16/9 + 1/9 + 25/9 = 42/9; divided by n - 1 = 2 gives 7/3.
    assert s.std == pytest.approx(math.sqrt(7.0 / 3.0))
    assert s.iqm == pytest.approx(7.0 / 3.0)
    # The bootstrap mean of 3 values can only range between the smallest and the largest value.
    assert 1.0 <= s.ci_low <= s.mean <= s.ci_high <= 4.0


def test_summarize_drops_non_finite_values():
    s = summarize([1.0, np.nan, 2.0, np.inf, 4.0])
    assert s.n == 3
    assert s.mean == pytest.approx(7.0 / 3.0)


def test_summarize_one_and_zero_values():
    one = summarize([0.7, np.nan])
    assert one == Summary(n=1, mean=0.7, std=0.0, iqm=0.7, ci_low=0.7, ci_high=0.7)
    none = summarize([np.nan])
    assert none.n == 0
    assert all(math.isnan(x) for x in (none.mean, none.std, none.iqm, none.ci_low, none.ci_high))
    assert summarize([]).n == 0


def test_summary_format():
    assert summarize([]).format() == "–"
    assert summarize([0.93]).format() == "0.93"
    assert summarize([0.93]).format(digits=3) == "0.930"
    s = Summary(n=3, mean=0.93, std=0.02, iqm=0.93, ci_low=0.904, ci_high=0.951)
    assert s.format() == "0.93 ± 0.02 [0.90, 0.95]"


def test_ci_of_a_constant_array_is_a_point():
    assert stratified_bootstrap_ci([0.5] * 7) == (0.5, 0.5)


def test_ci_of_two_values_spans_both_extremes():
    # Resampled means of [0, 1] are 0, 0.5 or 1 with probabilities 1/4, 1/2, 1/4, so the 2.5th
    # percentile is 0 and the 97.5th is 1.
    assert stratified_bootstrap_ci([0.0, 1.0], reps=4000) == (0.0, 1.0)
    s = summarize([0.0, 1.0], reps=4000)
    assert s.mean == pytest.approx(0.5)
    assert (s.ci_low, s.ci_high) == (0.0, 1.0)


def test_resampling_stays_within_each_task():
    # Every column is constant, so resampling runs within a column never changes it: the mean of
    # each replicate is exactly the overall mean.
    scores = np.tile([0.0, 1.0, 5.0], (4, 1))
    low, high = stratified_bootstrap_ci(scores)
    assert low == pytest.approx(2.0)
    assert high == pytest.approx(2.0)
    # Pooled into one stratum the same values mix across tasks and the interval opens up.
    pooled_low, pooled_high = stratified_bootstrap_ci(scores.reshape(-1))
    assert pooled_high - pooled_low > 1.0


def test_bootstrap_is_deterministic_for_a_seed():
    values = np.random.default_rng(3).normal(size=(6, 3))
    assert stratified_bootstrap_ci(values, seed=7) == stratified_bootstrap_ci(values, seed=7)
    assert stratified_bootstrap_ci(values, seed=7) != stratified_bootstrap_ci(values, seed=8)


def test_ci_shrinks_with_more_runs():
    rng = np.random.default_rng(0)
    small = rng.normal(size=5)
    large = rng.normal(size=200)
    low_s, high_s = stratified_bootstrap_ci(small)
    low_l, high_l = stratified_bootstrap_ci(large)
    assert high_l - low_l < 0.5 * (high_s - low_s)
    # For n = 200 standard normals the 95% interval of the mean is about 2 * 1.96 / sqrt(200).
    assert high_l - low_l == pytest.approx(2 * 1.96 / math.sqrt(200), rel=0.25)


def test_confidence_level_widens_the_interval():
    values = np.random.default_rng(1).normal(size=20)
    low90, high90 = stratified_bootstrap_ci(values, confidence=0.9)
    low99, high99 = stratified_bootstrap_ci(values, confidence=0.99)
    assert low99 < low90 < high90 < high99


def test_custom_statistic_without_axis_still_works():
    values = np.array([1.0, 2.0, 3.0, 4.0, 50.0])
    assert stratified_bootstrap_ci(values, statistic=lambda x: float(np.max(x))) == pytest.approx(
        stratified_bootstrap_ci(values, statistic=np.max)
    )


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="non-finite"):
        stratified_bootstrap_ci([[1.0, 2.0], [np.nan, 3.0]])
    with pytest.raises(ValueError):
        stratified_bootstrap_ci([])
    with pytest.raises(ValueError):
        stratified_bootstrap_ci([np.nan, np.inf])
    with pytest.raises(ValueError):
        stratified_bootstrap_ci(np.zeros((2, 2, 2)))
    with pytest.raises(ValueError):
        stratified_bootstrap_ci([1.0, 2.0], confidence=1.0)
    with pytest.raises(ValueError):
        aggregate([[1.0, np.nan]])


def test_one_dimensional_input_drops_nan_rows():
    assert stratified_bootstrap_ci([1.0, np.nan, 1.0]) == (1.0, 1.0)


def test_aggregate_point_estimates_pool_all_values():
    scores = np.array([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0], [6.0, 100.0]])
    result = aggregate(scores, reps=500)
    assert set(result) == {"mean", "iqm", "median"}
    assert result["mean"][0] == pytest.approx(121.0 / 8.0)
    # 8 values sorted 0..6, 100: drop two from each end, leaving 2, 3, 4, 5.
    assert result["iqm"][0] == pytest.approx(3.5)
    assert result["median"][0] == pytest.approx(3.5)
    for point, low, high in result.values():
        assert low <= point <= high


def test_aggregate_of_constant_columns_has_point_intervals():
    result = aggregate(np.tile([0.2, 0.8], (3, 1)))
    assert result["mean"] == pytest.approx((0.5, 0.5, 0.5))
