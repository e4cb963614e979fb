"""Tests of independence and normality of residuals (section 5.2.1–5.2.2).

The portmanteau test uses the sample autocorrelations (Ljung & Box, 1978); the
turning-point, difference-sign and rank tests are the i.i.d. tests of Brockwell
& Davis (1987, §1.6 / 9.4), each with its normal approximation; the
Kolmogorov–Smirnov test compares standardised residuals with N(0, 1).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats
from statsmodels.tsa.stattools import acf as _acf
from statsmodels.tsa.stattools import pacf as _pacf

from .series import TestResult, check_lags, residual_series


def _band(n: int, level: float) -> float:
    return float(stats.norm.ppf(1 - level / 2) / np.sqrt(n))


def acf(x, lags: int | None = None, level: float = 0.05) -> pd.DataFrame:
    """The sample autocorrelation at lags 1 to ``lags``, with the white-noise band ±z/√n.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    lags : int, optional
        The largest lag (default: from the series' length).
    level : float
        The band's significance level.

    Returns
    -------
    pandas.DataFrame
        ``acf`` and the band's ``lower`` and ``upper``, indexed by lag.
    """
    values = residual_series(x, 4)
    lags = check_lags(lags, len(values), 20)
    r = _acf(values, nlags=lags, fft=True)[1:]
    band = _band(len(values), level)
    return pd.DataFrame({"acf": r, "lower": -band, "upper": band}, index=pd.RangeIndex(1, lags + 1, name="lag"))


def pacf(x, lags: int | None = None, level: float = 0.05) -> pd.DataFrame:
    """The sample partial autocorrelation (Durbin–Levinson), with the band ±z/√n.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    lags : int, optional
        The largest lag (default: from the series' length).
    level : float
        The band's significance level.

    Returns
    -------
    pandas.DataFrame
        ``pacf`` and the band's ``lower`` and ``upper``, indexed by lag.
    """
    values = residual_series(x, 4)
    lags = check_lags(lags, len(values), 20)
    lags = min(lags, len(values) // 2 - 1)
    r = _pacf(values, nlags=lags, method="ldb")[1:]
    band = _band(len(values), level)
    return pd.DataFrame({"pacf": r, "lower": -band, "upper": band}, index=pd.RangeIndex(1, lags + 1, name="lag"))


def ljung_box(x, lags: int | None = None) -> TestResult:
    """The portmanteau test of white residuals: Q = n(n+2) Σ r_h²/(n−h) ~ χ²(lags).

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    lags : int, optional
        The number of autocorrelations summed (default: from the series' length).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    values = residual_series(x, 8)
    n = len(values)
    lags = check_lags(lags, n, 20)
    r = _acf(values, nlags=lags, fft=True)[1:]
    q = n * (n + 2) * np.sum(r**2 / (n - np.arange(1, lags + 1)))
    return TestResult("ljung_box", float(q), float(lags), float(stats.chi2.sf(q, lags)))


def _normal_test(name: str, observed: float, mean: float, variance: float) -> TestResult:
    z = (observed - mean) / np.sqrt(variance)
    return TestResult(name, float(z), np.nan, float(2 * stats.norm.sf(abs(z))))


def turning_point_test(x) -> TestResult:
    """The turning-point test of an i.i.d. series: T has mean 2(n−2)/3 and variance (16n−29)/90.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    values = residual_series(x, 8)
    n = len(values)
    a, b, c = values[:-2], values[1:-1], values[2:]
    turns = np.sum(((b > a) & (b > c)) | ((b < a) & (b < c)))
    return _normal_test("turning_points", turns, 2 * (n - 2) / 3, (16 * n - 29) / 90)


def difference_sign_test(x) -> TestResult:
    """The difference-sign test of an i.i.d. series: the increases S have mean (n−1)/2 and variance (n+1)/12.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    values = residual_series(x, 8)
    n = len(values)
    increases = np.sum(np.diff(values) > 0)
    return _normal_test("difference_sign", increases, (n - 1) / 2, (n + 1) / 12)


def rank_test(x) -> TestResult:
    """The rank test of a trend: the pairs i < j with x_j > x_i, P, have mean n(n−1)/4 and variance n(n−1)(2n+5)/72.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    values = residual_series(x, 8)
    n = len(values)
    pairs = n * (n - 1) / 2
    tau = stats.kendalltau(np.arange(n), values).statistic  # O(n log n) count of the pairs
    increasing = 0.5 * (tau * pairs + pairs)
    return _normal_test("rank", increasing, n * (n - 1) / 4, n * (n - 1) * (2 * n + 5) / 72)


def ks_normality(x, mean: float = 0.0, sd: float = 1.0) -> TestResult:
    """The Kolmogorov–Smirnov test of normality, D = sup |F_n − Φ| against N(mean, sd²) (5.2.2).

    Standardised residuals are N(0, 1) under the model, with nothing estimated from
    them, so the exact KS distribution applies.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    mean : float
        The normal distribution's mean.
    sd : float
        Its standard deviation.

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    values = residual_series(x, 8)
    res = stats.kstest((values - mean) / sd, "norm")
    return TestResult("ks_normality", float(res.statistic), np.nan, float(res.pvalue))
