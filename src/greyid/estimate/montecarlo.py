"""Monte Carlo validation of the estimator, as in thesis section 7.2 and A.7.

Simulate independent series from a model with known parameters, fit each, and
compare the mean estimate with the truth and the empirical variance of the
estimates with the mean of the estimated variances:

    Z_F = s_x² / s̄²  ~ F(n−1, ∞),      Z_t = |x̄ − x_sim| / (s_x / √n)  ~ t(n−1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import pandas as pd
from scipy import stats

from ..progress import track
from .calls import simulate_at
from .estimation import fit_model


@dataclass
class StudyResult:
    """The estimates of every series and the thesis-style summary table."""

    estimates: pd.DataFrame  # one row per series
    variances: pd.DataFrame  # estimated variances, one row per series
    truth: dict
    converged: np.ndarray
    residual_acf1: np.ndarray

    def table(self) -> pd.DataFrame:
        """x_sim, x̄, s_x², s̄², F and |t| statistics per quantity (tables 7.1, A.1)."""
        n = len(self.estimates)
        rows = {}
        for name in self.estimates.columns:
            x = self.estimates[name].to_numpy()
            s2 = np.var(x, ddof=1)
            sbar2 = np.nanmean(self.variances[name].to_numpy())
            rows[name] = {
                "x_sim": self.truth[name],
                "mean": x.mean(),
                "s2_empirical": s2,
                "s2_estimated": sbar2,
                "F": s2 / sbar2,
                "t": abs(x.mean() - self.truth[name]) / np.sqrt(s2 / n),
            }
        return pd.DataFrame.from_dict(rows, orient="index")

    def critical_values(self, alpha: float = 0.1) -> dict:
        """Acceptance regions of the F and t tests at level ``alpha``."""
        n = len(self.estimates)
        return {
            "F": (stats.f.ppf(alpha / 2, n - 1, 1e9), stats.f.ppf(1 - alpha / 2, n - 1, 1e9)),
            "t": stats.t.ppf(1 - alpha / 2, n - 1),
        }


def run_study(model, truth: Mapping[str, float], data: pd.DataFrame, n_series: int, report: list[str],
              derived: Mapping[str, str] | None = None, seed: int = 0, simulate: Mapping | None = None,
              fit: Mapping | None = None, progress: bool | Callable[[int, int], None] = False,
              simulation_model=None) -> StudyResult:
    """Simulate ``n_series`` series on ``data``'s times and inputs and fit each.

    ``report`` names the parameters for the table; ``derived`` adds functions of
    them (delta-method variances).  ``simulate`` and ``fit`` are keyword
    arguments for [`Model.simulate()`][greyid.api.Model.simulate] and
    [`Model.fit()`][greyid.api.Model.fit]; ``simulation_model``
    (default: ``model``) simulates, e.g. one whose initial state is known exactly
    while the fitted model keeps its prior.  ``progress=True``
    shows a progress bar; a callable receives ``(done, total)``.
    """
    simulate = dict(simulate or {})
    fit_options = dict(fit or {})
    sims = simulate_at(simulation_model or model, dict(truth), data, n_paths=n_series, seed=seed, **simulate)
    derived = dict(derived or {})
    estimates, variances, converged, acf1 = [], [], [], []
    for i in track(range(n_series), n_series, "Monte Carlo fits", progress):
        frame = data.copy()
        for j, name in enumerate(model.output_names):
            frame[name] = sims.outputs[i, :, j]
        result = fit_model(model, frame, **fit_options)
        est = {n: result.values[n] for n in report}
        var = {n: result.params.loc[n, "std_error"] ** 2 for n in report}
        if derived:
            d = result.derived(derived)
            est.update(d["estimate"].to_dict())
            var.update((d["std_error"] ** 2).to_dict())
        estimates.append(est)
        variances.append(var)
        converged.append(result.converged)
        res = result.residuals.iloc[:, 0].dropna().to_numpy()
        acf1.append(np.corrcoef(res[1:], res[:-1])[0, 1])
    truth_all = {n: float(truth[n]) for n in report}
    if derived:
        from ..model.equations import parse_expression

        for label, text in derived.items():
            expr = parse_expression(text, "derived quantity")
            truth_all[label] = float(expr.subs({s: truth[s.name] for s in expr.free_symbols}))
    return StudyResult(pd.DataFrame(estimates), pd.DataFrame(variances), truth_all, np.array(converged),
                       np.array(acf1))
