"""The bispectrum (5.14–5.15) and Hinich's (1982) tests of Gaussianity and linearity.

With X_j the DFT of the mean-removed series, F(j, k) = X_j X_k X̄_{j+k}/n is
the raw bispectrum at (ω_j, ω_k).  In the principal domain 0 < j < k,
j + k < n/2 the three frequencies differ, so for a Gaussian series the F(j, k)
are uncorrelated with variance S_j S_k S_{j+k}·n.  Normalised by a smoothed
spectrum Ŝ and averaged over squares of M × M frequency pairs,

    Z_s = Σ_{(j,k)∈s} F(j,k)/√(n Ŝ_j Ŝ_k Ŝ_{j+k}) / √(n_s)

is standard complex normal, so Σ_s 2|Z_s|² ~ χ²(2P) for a Gaussian series
(P squares).  For a linear series driven by i.i.d. noise the normalised
bispectrum is constant, so 2|Z_s|² ~ χ²(2, λ) with one λ for all full squares:
the linearity test compares the interquartile range of the 2|Z_s|² with that
of χ²(2, λ̂), λ̂ = mean − 2 (Hinich, 1982); a wider spread means nonlinearity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from ..errors import DataError
from .series import TestResult, residual_series

MINIMUM_LENGTH = 64


@dataclass(frozen=True)
class Bispectrum:
    """Square-averaged normalised bispectrum: one row per square of frequency pairs."""

    squares: pd.DataFrame  # f1, f2 (centres, cycles per time unit), n_pairs, z (complex), statistic 2|z|²
    side: int  # M, the side of a square in Fourier frequencies
    n: int


def _spectrum(X: np.ndarray, n: int, half_width: int) -> np.ndarray:
    """Daniell-smoothed periodogram at ordinates 0..n/2 (reflected at the ends)."""
    I = np.abs(X) ** 2 / n
    padded = np.concatenate([I[1: half_width + 1][::-1], I, I[-half_width - 1: -1][::-1]])
    window = np.ones(2 * half_width + 1) / (2 * half_width + 1)
    return np.convolve(padded, window, mode="valid")


def bispectrum(x, side: int | None = None, dt: float = 1.0) -> Bispectrum:
    """The normalised bispectrum, averaged over squares of ``side`` × ``side`` frequency pairs.

    Squares holding fewer than a quarter of their pairs inside the principal domain are left out.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    side : int, optional
        The squares' side (default ⌊n^0.5⌋, Hinich's choice).
    dt : float
        The sampling interval.

    Returns
    -------
    Bispectrum
        ``squares`` (each square's frequencies and normalised bispectrum), ``side`` and ``n``.
    """
    values = residual_series(x, MINIMUM_LENGTH, "series for the bispectrum")
    n = len(values)
    if side is None:
        side = int(np.sqrt(n))
    if not isinstance(side, (int, np.integer)) or side < 2:
        raise DataError(f"side must be an integer ≥ 2, got {side!r}")
    half = n // 2
    if side > half // 3:
        raise DataError(f"side={side} is too large for {n} values (at most {half // 3})")
    X = np.fft.fft(values - values.mean())
    S = _spectrum(X[: half + 1], n, max(2, side // 2))
    if np.any(S <= 0):
        raise DataError("the series has a zero spectrum at some frequency; the bispectrum cannot be normalised")
    j, k = np.meshgrid(np.arange(1, half), np.arange(1, half), indexing="ij")
    inside = (j < k) & (j + k < half)
    j, k = j[inside], k[inside]
    F = X[j] * X[k] * np.conj(X[j + k]) / n
    normalised = F / np.sqrt(n * S[j] * S[k] * S[j + k])
    stride = half // side + 2  # square (a, b) gets the key a·stride + b
    key = ((j - 1) // side) * stride + (k - 1) // side
    order = np.argsort(key, kind="stable")
    keys, start, counts = np.unique(key[order], return_index=True, return_counts=True)
    sums = np.add.reduceat(normalised[order], start)
    keep = counts >= side * side / 4
    keys, counts, sums = keys[keep], counts[keep], sums[keep]
    if len(keys) < 4:
        raise DataError(f"only {len(keys)} squares of side {side} fit in the principal domain; use a smaller side")
    z = sums / np.sqrt(counts)
    rows, cols = keys // stride, keys % stride
    squares = pd.DataFrame({
        "f1": (rows * side + (side + 1) / 2) / (n * dt),
        "f2": (cols * side + (side + 1) / 2) / (n * dt),
        "n_pairs": counts,
        "z": z,
        "statistic": 2 * np.abs(z) ** 2,
    })
    return Bispectrum(squares, int(side), n)


def gaussianity_test(x, side: int | None = None) -> TestResult:
    """Hinich's test of a zero bispectrum: Σ 2|Z_s|² ~ χ²(2P) for a Gaussian series.

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    side : int, optional
        The squares' side (default ⌊n^0.5⌋).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    b = bispectrum(x, side)
    stat = float(b.squares["statistic"].sum())
    df = 2.0 * len(b.squares)
    return TestResult("bispectrum_gaussianity", stat, df, float(stats.chi2.sf(stat, df)))


def _iqr_excess(values: np.ndarray) -> float:
    """Sample IQR of 2|Z_s|² minus the IQR of χ²(2, λ̂) at the moment estimate λ̂ (rows: replicates)."""
    lam = np.maximum(values.mean(axis=-1) - 2.0, 0.0)
    q1 = stats.ncx2.ppf(0.25, 2, np.maximum(lam, 1e-12))
    q3 = stats.ncx2.ppf(0.75, 2, np.maximum(lam, 1e-12))
    iqr = np.subtract(*np.percentile(values, [75, 25], axis=-1))
    return iqr - (q3 - q1)


def linearity_test(x, side: int | None = None, draws: int = 2000) -> TestResult:
    """Hinich's test of a constant normalised bispectrum (linearity), one-sided on the interquartile range.

    The statistic is the excess of the interquartile range of 2|Z_s|² over full
    squares above that of χ²(2, λ̂).  With the few squares a series of a few
    hundred values gives, the asymptotic law of the IQR is far off, so the p-value
    comes from ``draws`` samples of the χ²(2, λ̂) model itself (a fixed seed: the
    same series always gets the same p-value).

    Parameters
    ----------
    x : array_like or pandas.Series
        The series (standardised residuals; NaN where unobserved are left out).
    side : int, optional
        The squares' side (default ⌊n^0.5⌋).
    draws : int
        Samples of the null model.

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    b = bispectrum(x, side)
    full = b.squares[b.squares["n_pairs"] == b.side * b.side]["statistic"].to_numpy()
    if len(full) < 8:
        raise DataError(f"only {len(full)} full squares of side {b.side}; the linearity test needs 8 "
                        "(use a smaller side)")
    observed = float(_iqr_excess(full))
    lam = max(float(full.mean()) - 2.0, 0.0)
    rng = np.random.default_rng(12345)
    replicates = rng.noncentral_chisquare(2, lam, size=(draws, len(full))) if lam > 0 else \
        rng.chisquare(2, size=(draws, len(full)))
    excess = _iqr_excess(replicates)
    p = (1 + np.sum(excess >= observed)) / (draws + 1)
    return TestResult("bispectrum_linearity", observed, np.nan, float(p))
