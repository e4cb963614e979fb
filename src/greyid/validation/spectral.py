"""Frequency-domain residual analysis and residual–input dependence (5.2.2–5.2.3).

* The cumulative periodogram of white noise behaves like the empirical
  distribution of uniforms, so it is tested with the exact Kolmogorov–Smirnov
  distribution and drawn with KS bands (Brockwell & Davis, 1987, §10.2).
* Residuals independent of the inputs: the cross-correlation function, and the
  F test of the linear model (5.11) of the residuals on lagged inputs.
* Coherency (5.10) and multiple coherency (5.13) from Daniell-smoothed
  (2m + 1 ordinates) spectra; under zero coherency with q inputs,
  ((2m + 1 − q)/q)·W²/(1 − W²) ~ F(2q, 2(2m + 1 − q)), which for one input is
  (7.42): 2m W²/(1 − W²) ~ F(2, 4m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from ..errors import DataError
from .series import TestResult, check_lags, paired_series, residual_series


def _fourier(values: np.ndarray) -> tuple[np.ndarray, int]:
    """DFT ordinates j = 1..q of the mean-removed series, q = ⌊(n−1)/2⌋."""
    n = len(values)
    q = (n - 1) // 2
    return np.fft.rfft(values - values.mean())[1: q + 1], q


def periodogram(x, dt: float = 1.0) -> pd.Series:
    """The periodogram I(ω_j) = |Σ x_t e^{−iω_j t}|²/n at the Fourier frequencies j/(n·dt), j = 1 … ⌊(n−1)/2⌋.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    dt : float
        The sampling interval.

    Returns
    -------
    pandas.Series
        I, indexed by frequency.
    """
    values = residual_series(x, 8)
    X, q = _fourier(values)
    freq = np.arange(1, q + 1) / (len(values) * dt)
    return pd.Series(np.abs(X) ** 2 / len(values), index=pd.Index(freq, name="frequency"), name="periodogram")


def cumulative_periodogram(x, dt: float = 1.0, levels=(0.05, 0.01)) -> pd.DataFrame:
    """The cumulative periodogram C(ω_k) = Σ_{j≤k} I_j / Σ_j I_j, with the white-noise line and its KS bands.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    dt : float
        The sampling interval.
    levels : sequence of float
        The bands' significance levels.

    Returns
    -------
    pandas.DataFrame
        ``cumulative``, ``white`` (the white-noise line) and ``band_<level>`` per
        level, indexed by frequency.
    """
    I = periodogram(x, dt)
    q = len(I)
    if q < 3:
        raise DataError("the cumulative periodogram needs at least 7 observed values")
    out = pd.DataFrame({"cumulative": np.cumsum(I.to_numpy()) / I.sum(), "white": np.arange(1, q + 1) / q},
                       index=I.index)
    for level in levels:
        out[f"band_{1 - level:.0%}"] = stats.kstwo.ppf(1 - level, q - 1)
    return out


def cumulative_periodogram_test(x) -> TestResult:
    """The Kolmogorov–Smirnov test of the cumulative periodogram against the white-noise line.

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
    X, q = _fourier(values)
    I = np.abs(X) ** 2
    if q < 3:
        raise DataError("the cumulative periodogram test needs at least 7 observed values")
    # Under white noise C_1..C_{q−1} are distributed as ordered uniforms on (0, 1).
    c = np.cumsum(I)[:-1] / I.sum()
    res = stats.kstest(c, "uniform")
    return TestResult("cumulative_periodogram", float(res.statistic), float(q - 1), float(res.pvalue))


def cross_correlation(x, u, lags: int | None = None, level: float = 0.05) -> pd.DataFrame:
    """The cross-correlation r_εu(h) = corr(ε_{t+h}, u_t) for h = −lags … lags, with the band ±z/√n.

    Positive lags mean the input leads the residuals, which is where a missing
    input effect shows.  The band holds for white residuals independent of u.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    u : array_like
        The input.
    lags : int, optional
        The largest lag (default: from the series' length).
    level : float
        The band's significance level.

    Returns
    -------
    pandas.DataFrame
        ``ccf`` and the band's ``lower`` and ``upper``, indexed by lag.
    """
    a, b = paired_series(x, u, 8)
    n = len(a)
    lags = check_lags(lags, n, 20)
    a, b = a - a.mean(), b - b.mean()
    scale = n * np.sqrt(np.mean(a**2) * np.mean(b**2))
    if scale == 0:
        raise DataError("the residuals or the input are constant; their correlation is undefined")
    h = np.arange(-lags, lags + 1)
    r = np.array([np.sum(a[k:] * b[: n - k]) if k >= 0 else np.sum(a[: n + k] * b[-k:]) for k in h]) / scale
    band = float(stats.norm.ppf(1 - level / 2) / np.sqrt(n))
    return pd.DataFrame({"ccf": r, "lower": -band, "upper": band}, index=pd.Index(h, name="lag"))


def input_correlation_test(x, u, lags: int | None = None) -> TestResult:
    """The F test that the residuals do not depend linearly on u_t, …, u_{t−lags} (5.11).

    The residuals are regressed on an intercept and the lagged input; for white
    Gaussian residuals independent of the input the F statistic is exact.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    u : array_like
        The input.
    lags : int, optional
        The input's lags (default: from the series' length).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    a, b = paired_series(x, u, 12)
    n = len(a)
    lags = check_lags(lags, n, 10)
    if n - lags - 1 < lags + 4:
        raise DataError(f"lags={lags} leaves too few rows ({n - lags}) for the regression on the input")
    y = a[lags:]
    lagged = np.column_stack([b[lags - h: n - h] for h in range(lags + 1)])
    lagged = lagged - lagged.mean(axis=0)
    y = y - y.mean()
    rss0 = float(y @ y)
    coef, _, rank, _ = np.linalg.lstsq(lagged, y, rcond=None)
    if rank == 0:
        raise DataError("the input is constant over the residuals' rows; there is nothing to correlate")
    resid = y - lagged @ coef
    rss1 = float(resid @ resid)
    dof = len(y) - rank - 1
    f = ((rss0 - rss1) / rank) / (rss1 / dof)
    return TestResult("input_correlation", float(f), float(rank), float(stats.f.sf(f, rank, dof)))


@dataclass(frozen=True)
class Coherency:
    """Squared coherency per input and multiple coherency, at frequencies in cycles per time unit."""

    values: pd.DataFrame  # columns: one per input, and "multiple"
    critical: dict  # column → value of W² above which zero coherency is rejected at ``level``
    m: int
    level: float


def _default_m(n: int) -> int:
    return max(2, int(round(np.sqrt(n) / 4)))


def _smoothed_spectra(x, inputs, m):
    """Daniell-smoothed auto and cross spectra (2m + 1 ordinates) at the usable frequencies."""
    names, cols = _input_columns(inputs)
    a = np.asarray(x.to_numpy() if isinstance(x, pd.Series) else x, dtype=np.float64).ravel()
    if cols.shape[0] != len(a):
        raise DataError(f"the residuals ({len(a)} values) and the inputs ({cols.shape[0]} rows) differ in length")
    keep = ~(np.isnan(a) | np.isnan(cols).any(axis=1))
    a, cols = a[keep], cols[keep]
    n = len(a)
    if m is None:
        m = _default_m(n)
    if not isinstance(m, (int, np.integer)) or m < 1:
        raise DataError(f"m (the Daniell half-width) must be a positive integer, got {m!r}")
    q_in = cols.shape[1]
    if 2 * m + 1 <= q_in:
        raise DataError(f"m={m} averages {2 * m + 1} ordinates, too few for {q_in} inputs; use m ≥ {q_in // 2 + 1}")
    E, q = _fourier(a)
    if q < 2 * m + 1:
        raise DataError(f"m={m} needs at least {2 * (2 * m + 1) + 1} observed rows, the residuals have {n}")
    U = np.column_stack([_fourier(c)[0] for c in cols.T])
    window = np.ones(2 * m + 1) / (2 * m + 1)

    def smooth(v):
        return np.convolve(v, window, mode="valid")

    s_xx = smooth(np.abs(E) ** 2)
    s_ux = np.column_stack([smooth(U[:, i] * np.conj(E)) for i in range(q_in)])
    s_uu = np.array([[smooth(U[:, i] * np.conj(U[:, k])) for k in range(q_in)] for i in range(q_in)])
    s_uu = np.transpose(s_uu, (2, 0, 1))  # (frequency, i, k)
    freq_index = np.arange(m + 1, q - m + 1)
    return names, n, m, freq_index, s_xx, s_ux, s_uu


def _input_columns(inputs):
    if isinstance(inputs, pd.DataFrame):
        return list(inputs.columns), inputs.to_numpy(dtype=np.float64)
    if isinstance(inputs, pd.Series):
        return [inputs.name or "u"], inputs.to_numpy(dtype=np.float64)[:, None]
    arr = np.asarray(inputs, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    return [f"u{i + 1}" for i in range(arr.shape[1])], arr


def _multiple(s_xx, s_ux, s_uu):
    """W² = s_xu S_uu⁻¹ s_ux / s_xx at each frequency (5.13)."""
    sol = np.linalg.solve(s_uu, s_ux[..., None])[..., 0]
    explained = np.real(np.einsum("fi,fi->f", np.conj(s_ux), sol))
    return np.clip(explained / s_xx, 0.0, 1.0)


def _critical(q: int, ordinates: int, level: float) -> float:
    f = stats.f.ppf(1 - level, 2 * q, 2 * (ordinates - q))
    c = q / (ordinates - q) * f
    return float(c / (1 + c))


def coherency(x, inputs, m: int | None = None, dt: float = 1.0, level: float = 0.05) -> Coherency:
    """The squared coherency with each input (5.10) and the multiple coherency (5.13).

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    inputs : pandas.DataFrame, pandas.Series or array_like
        One column per input.
    m : int, optional
        The Daniell smoother's half-width (default ≈ √n/4).
    dt : float
        The sampling interval.
    level : float
        The significance level of ``critical``.

    Returns
    -------
    Coherency
        ``values`` (by frequency: each input's squared coherency and the multiple
        coherency), ``critical`` (the level of W² above which (7.42) rejects zero
        coherency at one frequency), ``m`` and ``level``.
    """
    names, n, m, j, s_xx, s_ux, s_uu = _smoothed_spectra(x, inputs, m)
    ordinates = 2 * m + 1
    cols = {}
    for i, name in enumerate(names):
        cols[name] = np.clip(np.abs(s_ux[:, i]) ** 2 / (s_xx * np.real(s_uu[:, i, i])), 0.0, 1.0)
    cols["multiple"] = _multiple(s_xx, s_ux, s_uu)
    critical = {name: _critical(1, ordinates, level) for name in names}
    critical["multiple"] = _critical(len(names), ordinates, level)
    values = pd.DataFrame(cols, index=pd.Index(j / (n * dt), name="frequency"))
    return Coherency(values, critical, m, level)


def coherency_test(x, inputs, m: int | None = None) -> TestResult:
    """The test of zero multiple coherency at all frequencies: (7.42) on independent bands, Šidák-combined.

    Smoothed estimates 2m + 1 ordinates apart share no periodogram ordinate and
    are independent; the smallest of their B p-values gives p = 1 − (1 − p_min)^B.
    The statistic reported is the largest multiple coherency among them.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    inputs : pandas.DataFrame, pandas.Series or array_like
        One column per input.
    m : int, optional
        The Daniell smoother's half-width (default ≈ √n/4).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    names, n, m, j, s_xx, s_ux, s_uu = _smoothed_spectra(x, inputs, m)
    ordinates, q = 2 * m + 1, len(names)
    bands = np.arange(0, len(j), ordinates)
    w2 = _multiple(s_xx[bands], s_ux[bands], s_uu[bands])
    f = (ordinates - q) / q * w2 / np.maximum(1 - w2, 1e-300)
    p = stats.f.sf(f, 2 * q, 2 * (ordinates - q))
    p_min = float(np.min(p))
    overall = -np.expm1(len(bands) * np.log1p(-min(p_min, 1 - 1e-16)))
    return TestResult("coherency", float(np.max(w2)), float(len(bands)), float(overall))
