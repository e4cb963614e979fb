"""How the estimates vary across a fleet: regression on covariates (thesis section 8.4).

The thesis relates the fuel-film model's X, τ_s and τ_ff at eleven operating
points to throttle angle, speed, manifold pressure and air flow by linear
regression over all subsets of the covariates, ranked by Mallows' C_p
(Weisberg 1985).  [`relate()`][greyid.fleet.population.relate] does the same on a fleet's table, by weighted
least squares with weights 1/SE² of the estimates (statsmodels), so a data set
that determines a parameter poorly counts for less.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import pandas as pd

from ..errors import DataError


@dataclass
class Relation:
    """All subsets of the covariates ranked by C_p; ``best`` is the fitted statsmodels WLS of the first."""

    parameter: str
    subsets: pd.DataFrame  # covariates, n_terms, cp, r2, aic; sorted by cp
    best: object  # statsmodels RegressionResults

    def summary(self) -> str:
        import warnings

        with warnings.catch_warnings():
            # statsmodels' table holds normality tests of the residuals that need 8 data sets or more; it
            # prints them as nan below that and warns, which a fleet of a few data sets always would.
            warnings.filterwarnings("ignore", message="omni_normtest is not valid")
            table = self.best.summary()
        return (f"{self.parameter}: best subset {list(self.best.model.exog_names[1:])} by Mallows' C_p\n"
                f"{self.subsets.to_string()}\n\n{table}")


def relate(fleet, covariates: pd.DataFrame, parameter: str, candidates=None, weighted: bool = True,
           max_terms: int | None = None) -> Relation:
    """Regress a parameter's estimates across a fleet on covariates of the data sets (section 8.4).

    The best subset of covariates by Mallows' C_p = RSS_p/σ̂² − n + 2p, with σ̂²
    the full model's residual mean square.

    Parameters
    ----------
    fleet : FleetResult or pandas.DataFrame
        The fleet, or its ``table``.
    covariates : pandas.DataFrame
        Indexed by the data sets' names.
    parameter : str
        The parameter whose estimates are regressed.
    candidates : sequence of str, optional
        The covariate columns to try (default: all).
    weighted : bool
        Weight each estimate by its inverse variance.
    max_terms : int, optional
        The largest subset tried (default: all candidates).

    Returns
    -------
    Relation
        ``subsets``: every subset of the covariates ranked by C_p (``covariates``,
        ``n_terms``, ``cp``, ``r2``, ``aic``; data sets without a fit are left out);
        ``best``: the fitted statsmodels WLS of the first; ``summary()``.

    Raises
    ------
    DataError
        An unknown parameter or covariate, data sets without a covariates row, a
        missing standard error with ``weighted=True``, or too few data sets for the
        covariates.
    """
    import statsmodels.api as sm

    table = getattr(fleet, "table", fleet)
    if parameter not in table.columns:
        raise DataError(f"'{parameter}' is not a parameter of the fleet's table; columns are {list(table.columns)}")
    candidates = list(covariates.columns if candidates is None else candidates)
    missing = [c for c in candidates if c not in covariates.columns]
    if missing:
        raise DataError(f"covariate '{missing[0]}' is not a column of covariates ({list(covariates.columns)})")
    unknown = [n for n in table.index if n not in covariates.index]
    if unknown:
        raise DataError(f"covariates have no row for data set '{unknown[0]}'")
    rows = table.index[table[parameter].notna()]
    frame = covariates.loc[rows, candidates].astype(float)
    y = table.loc[rows, parameter].astype(float)
    se = table.loc[rows, f"{parameter}_se"].astype(float) if f"{parameter}_se" in table else None
    keep = frame.notna().all(axis=1) & y.notna()
    if weighted:
        if se is None or not np.all(np.isfinite(se[keep])) or np.any(se[keep] <= 0):
            raise DataError(f"weighted regression needs a positive standard error of '{parameter}' for every "
                            "data set; use weighted=False")
    frame, y = frame[keep], y[keep]
    weights = 1.0 / se[keep] ** 2 if weighted else np.ones(len(y))
    n, full_terms = len(y), len(candidates) + 1
    if n <= full_terms:
        raise DataError(f"{n} data sets cannot support a regression on {len(candidates)} covariates")

    def wls(columns):
        X = sm.add_constant(frame[list(columns)], has_constant="add")
        return sm.WLS(y, X, weights=weights).fit()

    sigma2 = wls(candidates).mse_resid
    records, fitted = [], {}
    largest = len(candidates) if max_terms is None else min(max_terms, len(candidates))
    for k in range(largest + 1):
        for columns in combinations(candidates, k):
            result = wls(columns)
            p = k + 1
            cp = result.ssr / sigma2 - n + 2 * p
            fitted[columns] = result
            records.append(dict(covariates=", ".join(columns) or "(constant)", n_terms=p, cp=cp,
                                r2=result.rsquared, aic=result.aic, n=n))
    subsets = pd.DataFrame(records).sort_values("cp").reset_index(drop=True)
    order = sorted(fitted, key=lambda c: fitted[c].ssr / sigma2 - n + 2 * (len(c) + 1))
    return Relation(parameter, subsets, fitted[order[0]])
