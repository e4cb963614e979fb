"""Residual tests of chapter 5: size on white noise, power where they are meant to catch, bad input."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import signal, stats

from greyid import DataError
from greyid import validation as v

WHITE_TESTS = {
    "ljung_box": v.ljung_box,
    "turning_points": v.turning_point_test,
    "difference_sign": v.difference_sign_test,
    "rank": v.rank_test,
    "ks_normality": v.ks_normality,
    "cumulative_periodogram": v.cumulative_periodogram_test,
    "bispectrum_gaussianity": v.gaussianity_test,
    "bispectrum_linearity": v.linearity_test,
}


@pytest.fixture(scope="module")
def rejection_rates_white():
    """Rejection rates at 5 % over 400 seeded white-noise series of length 400."""
    rng = np.random.default_rng(2026)
    reps, n = 400, 400
    counts = dict.fromkeys(list(WHITE_TESTS) + ["input_correlation", "coherency"], 0)
    t = np.arange(n)
    for _ in range(reps):
        x = rng.normal(size=n)
        # Autocorrelated inputs (a random walk and a daily-like cycle), independent of x.
        u = np.column_stack([np.cumsum(rng.normal(size=n)) * 0.1 + np.sin(2 * np.pi * t / 48),
                             signal.lfilter([1], [1, -0.8], rng.normal(size=n))])
        for name, test in WHITE_TESTS.items():
            counts[name] += test(x).p_value < 0.05
        counts["input_correlation"] += v.input_correlation_test(x, u[:, 0]).p_value < 0.05
        counts["coherency"] += v.coherency_test(x, u).p_value < 0.05
    return {k: c / reps for k, c in counts.items()}


@pytest.mark.parametrize("name", list(WHITE_TESTS) + ["input_correlation", "coherency"])
def test_size_on_white_noise(rejection_rates_white, name):
    # 400 replicates: the Monte Carlo standard error of a 5 % rate is 1.1 %.
    assert 0.015 <= rejection_rates_white[name] <= 0.085, rejection_rates_white[name]


def _power(make, test, reps=60, seed=7):
    rng = np.random.default_rng(seed)
    return np.mean([test(*make(rng)).p_value < 0.05 for _ in range(reps)])


def test_power_against_ar1():
    def ar1(rng):
        return (signal.lfilter([1], [1, -0.4], rng.normal(size=500)),)

    assert _power(ar1, v.ljung_box) > 0.95
    assert _power(ar1, v.cumulative_periodogram_test) > 0.95
    assert _power(ar1, v.turning_point_test) > 0.8


def test_power_against_input_dependence():
    def with_input(rng):
        u = signal.lfilter([1], [1, -0.5], rng.normal(size=500))
        return rng.normal(size=500) + 0.25 * np.concatenate([[0.0], u[:-1]]), u

    assert _power(with_input, v.input_correlation_test) > 0.95
    assert _power(with_input, lambda x, u: v.ljung_box(x)) < 0.2  # the residuals alone look white


def test_power_against_quadratic_nonlinearity():
    def quadratic(rng):
        e = rng.normal(size=501)
        return (e[1:] + 0.6 * (e[:-1] ** 2 - 1),)

    assert _power(quadratic, v.gaussianity_test) > 0.95
    assert _power(quadratic, v.ljung_box) < 0.2  # uncorrelated, so second-order tests are blind


def test_power_against_trend():
    def trend(rng):
        return (rng.normal(size=500) + np.linspace(0, 0.6, 500),)

    assert _power(trend, v.rank_test) > 0.8


def test_statistics_match_direct_formulas():
    rng = np.random.default_rng(3)
    x = rng.normal(size=300)
    n = len(x)
    # Ljung–Box from the textbook definition of the sample autocorrelation.
    xc = x - x.mean()
    r = np.array([np.sum(xc[h:] * xc[:-h]) for h in range(1, 11)]) / np.sum(xc**2)
    q = n * (n + 2) * np.sum(r**2 / (n - np.arange(1, 11)))
    assert v.ljung_box(x, 10).statistic == pytest.approx(q, rel=1e-10)
    # Rank test: count the increasing pairs directly.
    pairs = sum(np.sum(x[i + 1:] > x[i]) for i in range(n))
    z = (pairs - n * (n - 1) / 4) / np.sqrt(n * (n - 1) * (2 * n + 5) / 72)
    assert v.rank_test(x).statistic == pytest.approx(z, rel=1e-10)
    # Turning points counted in a loop.
    turns = sum((x[i] > x[i - 1]) == (x[i] > x[i + 1]) for i in range(1, n - 1))
    assert v.turning_point_test(x).statistic == pytest.approx((turns - 2 * (n - 2) / 3) / np.sqrt((16 * n - 29) / 90))
    # Cross-correlation at lag 2 (input leads) from its definition.
    u = rng.normal(size=n)
    uc = u - u.mean()
    cc = v.cross_correlation(x, u, 5)
    assert cc.loc[2, "ccf"] == pytest.approx(np.sum(xc[2:] * uc[:-2]) / np.sqrt(np.sum(xc**2) * np.sum(uc**2)))


def test_coherency_critical_level_is_742():
    # (7.42): 2m W²/(1 − W²) ~ F(2, 4m) for one input, so W²_crit = F/(2m + F).
    rng = np.random.default_rng(5)
    x, u = rng.normal(size=600), rng.normal(size=600)
    coh = v.coherency(x, u, m=6, level=0.05)
    f = stats.f.ppf(0.95, 2, 24)
    assert coh.critical["u1"] == pytest.approx(f / (12 + f))
    # With one input the multiple coherency is the ordinary coherency.
    np.testing.assert_allclose(coh.values["multiple"], coh.values["u1"], rtol=1e-10)
    # A direct Daniell estimate at one frequency.
    X, U = np.fft.rfft(x - x.mean()), np.fft.rfft(u - u.mean())
    j = 40
    sl = slice(j - 6, j + 7)
    w2 = abs(np.sum(X[sl] * np.conj(U[sl]))) ** 2 / (np.sum(abs(X[sl]) ** 2) * np.sum(abs(U[sl]) ** 2))
    assert coh.values["u1"].loc[j / 600] == pytest.approx(w2, rel=1e-10)


def test_bispectrum_of_skewed_iid_noise_matches_third_moment():
    # For i.i.d. noise the bispectrum is flat at μ₃, so E z_s = √n_s μ₃/(σ³√n) in every square.
    rng = np.random.default_rng(11)
    n = 4096
    x = rng.exponential(size=n) - 1.0  # σ = 1, μ₃ = 2
    b = v.bispectrum(x, side=32)
    estimate = np.mean(np.real(b.squares["z"]) / np.sqrt(b.squares["n_pairs"])) * np.sqrt(n)
    assert estimate == pytest.approx(2.0, rel=0.15)
    assert abs(np.mean(np.imag(b.squares["z"]) / np.sqrt(b.squares["n_pairs"])) * np.sqrt(n)) < 0.3


def test_cumulative_periodogram_bands_are_ks_quantiles():
    x = np.random.default_rng(2).normal(size=201)
    cp = v.cumulative_periodogram(x)
    q = len(cp)
    assert q == 100
    assert cp["band_95%"].iloc[0] == pytest.approx(stats.kstwo.ppf(0.95, q - 1))
    assert cp["cumulative"].iloc[-1] == pytest.approx(1.0)


def test_nan_values_are_dropped_as_documented():
    rng = np.random.default_rng(4)
    x = rng.normal(size=300)
    gappy = x.copy()
    gappy[[5, 50, 51, 200]] = np.nan
    kept = x[~np.isnan(gappy)]
    for test in (v.ljung_box, v.turning_point_test, v.ks_normality, v.cumulative_periodogram_test):
        assert test(pd.Series(gappy)).statistic == test(kept).statistic


def test_bad_input_is_rejected_clearly():
    with pytest.raises(DataError, match="needs at least"):
        v.ljung_box([0.1, 0.2, 0.3])
    with pytest.raises(DataError, match="beyond the data"):
        v.ljung_box(np.random.default_rng(0).normal(size=50), lags=60)
    with pytest.raises(DataError, match="infinite value at position 3"):
        v.rank_test([0.0, 1.0, 2.0, np.inf] + [0.5] * 10)
    with pytest.raises(DataError, match="one-dimensional"):
        v.ks_normality(np.zeros((10, 3)))
    with pytest.raises(DataError, match="differ in length"):
        v.input_correlation_test(np.zeros(100), np.zeros(90))
    with pytest.raises(DataError, match="needs at least 64"):
        v.gaussianity_test(np.random.default_rng(0).normal(size=40))
    with pytest.raises(DataError, match="m=.* needs at least"):
        v.coherency_test(np.random.default_rng(0).normal(size=30), np.random.default_rng(1).normal(size=30), m=10)
