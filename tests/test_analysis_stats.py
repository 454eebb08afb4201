"""dyq.analysis.stats: Wilson intervals, the exact McNemar comparison, correlations, bootstrap."""
import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dyq.analysis import bootstrap_ci, mcnemar_exact, paired_comparison, pearson, spearman, wilson_interval

counts = st.integers(1, 500).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n)))
paired = st.integers(1, 40).flatmap(lambda n: st.tuples(st.lists(st.booleans(), min_size=n, max_size=n),
                                                         st.lists(st.booleans(), min_size=n, max_size=n)))
integer_series = st.lists(st.tuples(st.integers(-30, 30), st.integers(-30, 30)), min_size=2, max_size=40)


def brute_force_mcnemar(a_only, b_only):
    """Two-sided exact binomial test at 1/2: the total probability of outcomes no likelier than the observed."""
    m = a_only + b_only
    probability = [Fraction(math.comb(m, i), 2**m) for i in range(m + 1)]
    observed = probability[a_only]
    return float(sum(p for p in probability if p <= observed))


def test_wilson_matches_a_hand_checked_case():
    low, high = wilson_interval(3, 10)
    assert low == pytest.approx(0.10779, abs=1e-5) and high == pytest.approx(0.60323, abs=1e-5)


def test_wilson_with_no_successes_starts_at_zero():
    low, high = wilson_interval(0, 10)
    assert low == 0.0 and high == pytest.approx(1.96**2 / (10 + 1.96**2))


@given(counts)
def test_wilson_interval_contains_the_point_estimate(case):
    successes, n = case
    low, high = wilson_interval(successes, n)
    assert 0.0 <= low <= successes / n <= high <= 1.0


@pytest.mark.parametrize("successes, n, z, match", [
    (1, 0, 1.96, "n must be an int >= 1"),
    (11, 10, 1.96, "successes must be <= n"),
    (-1, 10, 1.96, "successes must be an int >= 0"),
    (1, 10, 0.0, "z must be > 0"),
])
def test_wilson_rejects_bad_counts(successes, n, z, match):
    with pytest.raises(ValueError, match=match):
        wilson_interval(successes, n, z)


def test_wilson_rejects_a_fractional_count():
    with pytest.raises(TypeError, match="successes must be an int"):
        wilson_interval(2.5, 10)


@given(st.integers(0, 60), st.integers(0, 60))
def test_mcnemar_is_the_exact_binomial_test(a_only, b_only):
    assert mcnemar_exact(a_only, b_only) == pytest.approx(brute_force_mcnemar(a_only, b_only), rel=1e-12)


def test_mcnemar_matches_scipy():
    scipy_stats = pytest.importorskip("scipy.stats")
    for a_only, b_only in [(0, 5), (9, 1), (12, 30), (7, 7)]:
        expected = scipy_stats.binomtest(a_only, a_only + b_only, 0.5).pvalue
        assert mcnemar_exact(a_only, b_only) == pytest.approx(expected, rel=1e-9)


@given(paired)
def test_paired_p_value_is_a_probability_and_symmetric(case):
    a, b = case
    forward, backward = paired_comparison(a, b), paired_comparison(b, a)
    assert 0.0 <= forward["p_value"] <= 1.0
    assert forward["p_value"] == backward["p_value"]
    assert (forward["a_only"], forward["b_only"]) == (backward["b_only"], backward["a_only"])


def test_paired_counts_discordant_seeds_and_resolves_a_clear_win():
    a = np.array([True] * 12 + [False] * 3)
    b = np.array([False] * 10 + [True] * 2 + [False] * 3)
    result = paired_comparison(a, b)
    assert result == {"n": 15, "successes_a": 12, "successes_b": 2, "a_only": 10, "b_only": 0,
                      "p_value": 2 / 1024, "verdict": "resolved: A better"}


def test_paired_without_discordant_seeds_is_not_resolved():
    result = paired_comparison([1, 0, 1], [1, 0, 1])
    assert result["p_value"] == 1.0 and result["verdict"] == "not resolved"


def test_paired_names_the_better_arm_b():
    assert paired_comparison([False] * 8, [True] * 8)["verdict"] == "resolved: B better"


@pytest.mark.parametrize("a, b, match", [
    ([True, False], [True], "a and b must have the same length"),
    ([], [], "a must be a non-empty 1-D array"),
    ([0.5, 1.0], [1, 0], "a must hold booleans"),
    ([[True]], [[True]], "a must be a non-empty 1-D array"),
])
def test_paired_rejects_bad_success_arrays(a, b, match):
    with pytest.raises(ValueError, match=match):
        paired_comparison(a, b)


def test_pearson_matches_numpy(rng):
    x = np.random.default_rng(rng.initial_seed()).normal(size=50)
    y = 0.3 * x + np.random.default_rng(rng.initial_seed() + 1).normal(size=50)
    assert pearson(x, y) == pytest.approx(np.corrcoef(x, y)[0, 1], abs=1e-12)


def test_pearson_of_a_linear_function_is_one():
    x = np.linspace(-1.0, 2.0, 17)
    assert pearson(x, 3.0 * x + 1.0) == pytest.approx(1.0)
    assert pearson(x, -0.5 * x) == pytest.approx(-1.0)


def test_correlation_of_a_constant_is_undefined():
    assert math.isnan(pearson([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]))
    assert math.isnan(spearman([1.0, 2.0, 3.0], [4.0, 4.0, 4.0]))


def test_spearman_averages_tied_ranks():
    # ranks x = (1, 2.5, 2.5, 4), y = (1, 3, 2, 4): r = 4.5 / sqrt(4.5 * 5) by hand
    assert spearman([1, 2, 2, 3], [1, 3, 2, 4]) == pytest.approx(4.5 / math.sqrt(4.5 * 5.0))


def test_spearman_of_a_monotone_function_is_one():
    x = np.linspace(0.0, 3.0, 20)
    assert spearman(x, np.exp(4.0 * x)) == pytest.approx(1.0)


@given(integer_series)
def test_spearman_is_invariant_under_monotone_transforms(pairs):
    x, y = (np.array(column, dtype=float) for column in zip(*pairs))
    expected = spearman(x, y)
    transformed = spearman(x**3 + 2.0 * x, np.exp(y / 10.0))
    assert (math.isnan(expected) and math.isnan(transformed)) or transformed == pytest.approx(expected, abs=1e-12)


def test_spearman_matches_scipy(rng):
    scipy_stats = pytest.importorskip("scipy.stats")
    draw = np.random.default_rng(rng.initial_seed())
    x, y = draw.integers(0, 6, 40).astype(float), draw.integers(0, 6, 40).astype(float)
    assert spearman(x, y) == pytest.approx(scipy_stats.spearmanr(x, y).statistic, abs=1e-12)


@pytest.mark.parametrize("x, y, match", [
    ([1.0, 2.0, 3.0], [1.0, 2.0], "x and y must have the same length"),
    ([1.0], [1.0], "x must have at least 2 entries"),
    ([1.0, math.nan], [1.0, 2.0], "x must be finite"),
    ([[1.0, 2.0]], [[1.0, 2.0]], "x must be 1-D"),
])
@pytest.mark.parametrize("statistic", [pearson, spearman])
def test_correlations_reject_bad_series(statistic, x, y, match):
    with pytest.raises(ValueError, match=match):
        statistic(x, y)


def test_bootstrap_is_deterministic_and_brackets_a_strong_correlation():
    x = np.linspace(0.0, 1.0, 40)
    y = x + 0.05 * np.sin(37.0 * x)
    first, second = bootstrap_ci(x, y, pearson, n_boot=300), bootstrap_ci(x, y, pearson, n_boot=300)
    assert first == second
    assert first.low <= pearson(x, y) <= first.high and first.low > 0.9


def test_bootstrap_skips_and_counts_degenerate_resamples():
    interval = bootstrap_ci([0.0, 1.0], [0.0, 1.0], pearson, n_boot=400)
    assert 0 < interval.skipped < 400 and interval.resamples + interval.skipped == 400
    assert interval.low == interval.high == pytest.approx(1.0)


def test_bootstrap_with_every_resample_degenerate_is_nan():
    interval = bootstrap_ci([2.0, 2.0, 2.0], [1.0, 2.0, 3.0], spearman, n_boot=50)
    assert math.isnan(interval.low) and math.isnan(interval.high) and interval.skipped == 50


@pytest.mark.parametrize("kwargs, match", [({"level": 1.0}, "level must be in"), ({"n_boot": 0}, "n_boot must be")])
def test_bootstrap_rejects_bad_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        bootstrap_ci([0.0, 1.0, 2.0], [1.0, 0.0, 2.0], pearson, **kwargs)


def test_mcnemar_beyond_the_exact_sum_matches_it_and_stays_fast():
    """Past EXACT_MCNEMAR_MAX discordant seeds the p-value is summed in logarithms: it matches the exact big-
    integer sum where both run, and a million seeds take well under a second (the exact sum took minutes)."""
    import time

    from dyq.analysis import stats

    for a_only, b_only in [(1001, 1100), (1400, 1500), (2100, 2300)]:
        exact = 2 * sum(math.comb(a_only + b_only, i) for i in range(min(a_only, b_only) + 1)) / 2 ** (a_only + b_only)
        assert a_only + b_only > stats.EXACT_MCNEMAR_MAX
        assert mcnemar_exact(a_only, b_only) == pytest.approx(min(1.0, exact), rel=1e-9)
    start = time.perf_counter()
    assert mcnemar_exact(10**6, 10**6) == pytest.approx(1.0)
    assert mcnemar_exact(10**6 - 5000, 10**6) < 1e-3
    assert time.perf_counter() - start < 5.0


def test_alpha_outside_zero_one_is_refused():
    with pytest.raises(ValueError, match=r"alpha must be in \(0, 1\), got 1.5"):
        paired_comparison([1, 0, 1], [1, 0, 1], alpha=1.5)


def test_pearson_near_the_ends_of_float64():
    x = np.array([1.0, 2.0, 3.5])
    assert pearson(x * 1e200, [1, 2, 3]) == pytest.approx(pearson(x, [1, 2, 3]), abs=1e-12)
    assert pearson(x * 1e-170, [1, 2, 3]) == pytest.approx(pearson(x, [1, 2, 3]), abs=1e-12)
    assert spearman(x * 1e300, [1, 2, 3]) == pytest.approx(1.0)
