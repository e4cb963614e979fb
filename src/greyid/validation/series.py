"""The common ground of the residual tests: a test's result, and checked input series.

Every test takes a plain residual series (a NumPy array, a list or a pandas
Series).  NaN marks an unobserved value (a fit's residuals are NaN where an
output was not measured); the tests drop those values and treat the remaining
ones as consecutive.  That keeps the null distribution of i.i.d. or white
residuals intact; with many gaps the lags and frequencies are approximate.
Infinite values are an error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..errors import DataError


@dataclass(frozen=True)
class TestResult:
    """A statistic with its null distribution's degrees of freedom and p-value."""

    __test__ = False  # not a pytest test class

    test: str
    statistic: float
    df: float
    p_value: float

    def reject(self, level: float = 0.05) -> bool:
        """Whether the null hypothesis is rejected.

        Parameters
        ----------
        level : float
            The significance level.

        Returns
        -------
        bool
            ``p_value < level``.
        """
        return bool(self.p_value < level)

    def __repr__(self) -> str:
        df = "" if np.isnan(self.df) else f", df={self.df:g}"
        return f"<{self.test}: statistic={self.statistic:.4g}{df}, p_value={self.p_value:.4g}>"


def residual_series(x, minimum: int, what: str = "residual series") -> np.ndarray:
    """``x`` as a 1-D float array with NaN removed; at least ``minimum`` values left."""
    values = np.asarray(x.to_numpy() if isinstance(x, (pd.Series, pd.DataFrame)) else x, dtype=np.float64)
    if values.ndim == 2 and 1 in values.shape:
        values = values.ravel()
    if values.ndim != 1:
        raise DataError(f"the {what} must be one-dimensional, got shape {values.shape}")
    if np.any(np.isinf(values)):
        row = int(np.flatnonzero(np.isinf(values))[0])
        raise DataError(f"the {what} has an infinite value at position {row}")
    values = values[~np.isnan(values)]
    if len(values) < minimum:
        raise DataError(f"the {what} has {len(values)} observed values; this test needs at least {minimum}")
    return values


def paired_series(x, u, minimum: int, what: str = "input") -> tuple[np.ndarray, np.ndarray]:
    """Residuals and one input on the rows where both are observed (NaN in either removed)."""
    a = np.asarray(x.to_numpy() if isinstance(x, pd.Series) else x, dtype=np.float64).ravel()
    b = np.asarray(u.to_numpy() if isinstance(u, pd.Series) else u, dtype=np.float64).ravel()
    if len(a) != len(b):
        raise DataError(f"the residuals ({len(a)} values) and the {what} ({len(b)} values) differ in length")
    keep = ~(np.isnan(a) | np.isnan(b))
    a, b = a[keep], b[keep]
    if np.any(np.isinf(a)) or np.any(np.isinf(b)):
        raise DataError(f"the residuals or the {what} have an infinite value")
    if len(a) < minimum:
        raise DataError(f"the residuals and the {what} have {len(a)} rows observed together; "
                        f"this test needs at least {minimum}")
    return a, b


def check_lags(lags, n: int, default: int, what: str = "lags") -> int:
    """A lag count between 1 and n − 2 (default ``default``, capped for short series)."""
    if lags is None:
        return max(1, min(default, n // 5))
    if not isinstance(lags, (int, np.integer)) or lags < 1:
        raise DataError(f"{what} must be a positive integer, got {lags!r}")
    if lags > n - 2:
        raise DataError(f"{what}={lags} is beyond the data: the series has {n} observed values "
                        f"(use at most {n - 2})")
    return int(lags)
