"""Monte Carlo validation of the estimator, as in thesis section 7.2 and A.7.

Simulate independent series from a model with known parameters, fit each, and
compare the mean estimate with the truth and the empirical variance of the
estimates with the mean of the estimated variances:

    Z_F = s_x² / s̄²  ~ F(n−1, ∞),      Z_t = |x̄ − x_sim| / (s_x / √n)  ~ t(n−1).

The series are fitted as a fleet ([`fit_many()`][greyid.fleet.fit.fit_many]): they share the model, the
times and the inputs, so their searches run together, each request evaluated for every series by one
program vectorised over them, and each series' fit is the one a separate ``model.fit`` gives.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import pandas as pd

from ..errors import ModelError
from ..estimate.calls import simulate_at
from ..estimate.estimation import fit_model
from ..model.options import resolve
from ..progress import track
from .fit import fit_many


@dataclass
class StudyResult:
    """The estimates of every series of a [`run_study()`][greyid.fleet.study.run_study] and the thesis-style
    summary table.

    Attributes
    ----------
    estimates : pandas.DataFrame
        One row per series, one column per reported quantity.
    variances : pandas.DataFrame
        The estimated variances (squared standard errors), laid out as ``estimates``.
    truth : dict
        The simulated value of each quantity.
    converged : numpy.ndarray
        Whether each series' fit converged.
    residual_acf1 : numpy.ndarray
        The lag-1 autocorrelation of each fit's first output's residuals.
    """

    estimates: pd.DataFrame
    variances: pd.DataFrame
    truth: dict
    converged: np.ndarray
    residual_acf1: np.ndarray

    def table(self) -> pd.DataFrame:
        """The thesis' table: x_sim, x̄, s_x², s̄², F and |t| per quantity (tables 7.1, A.1; Z_F and Z_t above).

        Returns
        -------
        pandas.DataFrame
            One row per quantity; columns ``x_sim``, ``mean``, ``s2_empirical``, ``s2_estimated``, ``F``, ``t``.
        """
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
        """Acceptance regions of the F and t tests at level ``alpha``.

        Parameters
        ----------
        alpha : float
            The tests' level.

        Returns
        -------
        dict
            ``{"F": (lower, upper), "t": upper}``.
        """
        from scipy import stats  # here: scipy.stats costs half a second to import, and fit_many needs none

        n = len(self.estimates)
        return {
            "F": (stats.f.ppf(alpha / 2, n - 1, 1e9), stats.f.ppf(1 - alpha / 2, n - 1, 1e9)),
            "t": stats.t.ppf(1 - alpha / 2, n - 1),
        }


def simulated_series(model, truth: Mapping[str, float], data: pd.DataFrame, n_series: int, seed: int = 0,
                     **simulate) -> list[pd.DataFrame]:
    """``data`` with its outputs replaced by each of ``n_series`` paths simulated at ``truth`` (the series
    of [`run_study()`][greyid.fleet.study.run_study]).

    Parameters
    ----------
    model : Model
        The model that simulates.
    truth : mapping
        Its parameters.
    data : pandas.DataFrame
        The times and inputs; every other column is kept as it is.
    n_series : int
        How many paths.
    seed : int
        Seed of the simulation.
    **simulate
        Settings of [`Model.simulate()`][greyid.api.Model.simulate] (``method``, ``substeps``).

    Returns
    -------
    list of pandas.DataFrame
        One frame per path.
    """
    sims = simulate_at(model, dict(truth), data, n_paths=n_series, seed=seed, **simulate)
    frames = []
    for i in range(n_series):
        frame = data.copy()
        for j, name in enumerate(model.output_names):
            frame[name] = sims.outputs[i, :, j]
        frames.append(frame)
    return frames


def run_study(model, truth: Mapping[str, float], data: pd.DataFrame, n_series: int, report: list[str],
              derived: Mapping[str, str] | None = None, seed: int = 0, simulate: Mapping | None = None,
              fit: Mapping | None = None, progress: bool | Callable[[int, int], None] = False,
              simulation_model=None, scheduler=None) -> StudyResult:
    """Simulate ``n_series`` series on ``data``'s times and inputs and fit each (tables 7.1, A.1).

    Parameters
    ----------
    model : Model
        The model fitted to each series.
    truth : mapping
        The parameters the series are simulated with (every parameter of ``simulation_model``).
    data : pandas.DataFrame
        The times and inputs of every series (output columns, if any, are replaced).
    n_series : int
        How many series to simulate and fit.
    report : list of str
        The parameters in the table.
    derived : mapping, optional
        Label → expression in the parameters, added to the table with delta-method variances.
    seed : int
        Seed of the simulation.
    simulate : mapping, optional
        Keyword arguments of [`Model.simulate()`][greyid.api.Model.simulate] (``method``, ``substeps``).
    fit : mapping, optional
        Keyword arguments of [`Model.fit()`][greyid.api.Model.fit] (``method``, ``horizon``,
        ``cov_type``, ...).  With ``steady_state=True`` the series are fitted one after the
        other (a single fit's setting), otherwise together.
    progress : bool or callable
        A progress bar over the fitted series; a callable receives ``(done, total)``.
    simulation_model : Model, optional
        The model that simulates (default ``model``), e.g. one whose initial state is known
        exactly while the fitted model keeps its prior.
    scheduler : dask.distributed.Client, optional
        Fit the series on a Dask cluster ([`fit_many()`][greyid.fleet.fit.fit_many]); not with
        ``steady_state=True``.

    Returns
    -------
    StudyResult
        Every series' estimates and estimated variances, and the summary table.

    Raises
    ------
    ModelError
        A series whose fit failed (named by its number), or ``scheduler`` with ``steady_state=True``.

    Examples
    --------
    >>> from greyid.datasets import thesis
    >>> from greyid.fleet.study import run_study
    >>> study = run_study(thesis.test_cell_model(), thesis.TEST_CELL_PARAMETERS,
    ...                   thesis.test_cell_inputs(), 6, report=["Hi", "Ci"], seed=11,
    ...                   simulate={"method": "exact"})
    >>> list(study.table().index)
    ['Hi', 'Ci']
    """
    simulate = dict(simulate or {})
    fit_options = dict(fit or {})
    # Given in ``fit``, else the model's own setting (a model file's ``steady_state = true``).
    steady_state = bool(resolve(model._options, fit_options, ("steady_state",)).get("steady_state"))
    if steady_state and scheduler is not None:
        raise ModelError("steady_state=True fits the series one after the other in this process; "
                         "leave out scheduler, or steady_state to fit them together on the cluster")
    frames = simulated_series(simulation_model or model, truth, data, n_series, seed, **simulate)
    if steady_state:
        # A single fit's setting (a fleet evaluates its members together, where each one's switch
        # would run both forms): the series are fitted one after the other.
        fits = [fit_model(model, frame, **fit_options) for frame in track(frames, n_series, "Monte Carlo fits",
                                                                          progress)]
    else:
        fleet = fit_many(model, frames, scheduler=scheduler, progress=progress, **fit_options)
        for series, error in fleet.failed.items():  # the first that failed; a study needs every series
            raise ModelError(f"Monte Carlo series {series} (simulated with seed {seed}): {error}")
        fits = [fleet.fits[i] for i in range(n_series)]
    derived = dict(derived or {})
    estimates, variances, converged, acf1 = [], [], [], []
    for i in range(n_series):
        result = fits[i]
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
