"""The result of a fleet fit: one row per data set, and each data set's fit."""

from __future__ import annotations

import numpy as np
import pandas as pd


class FleetResult:
    """Estimates of one model on many data sets.

    Made by [`fit_many()`][greyid.fleet.fit.fit_many].

    Parameters
    ----------
    model : Model
        The model fitted.
    names : list
        The data sets' names.
    rows : list of dict
        Per data set, ``{"error": message}`` where it has no fit.
    fits : list
        Per data set, its [`FitResult`][greyid.api.FitResult] or None.

    Attributes
    ----------
    table : pandas.DataFrame
        One row per data set (index: the names) with a column per parameter (its
        estimate), ``<parameter>_se`` (standard errors), ``loglik``, ``aic``,
        ``n_obs``, ``converged``, ``iterations``, ``message`` and ``error`` (why a
        data set has no fit, else None).
    fits : dict
        Name → [`FitResult`][greyid.api.FitResult], None where the data set failed.
    """

    def __init__(self, model, names: list, rows: list[dict], fits: list):
        self.model = model
        self.fits = dict(zip(names, fits))
        parameters = list(model.parameter_names)
        records = []
        for row, fit in zip(rows, fits):
            record = {p: np.nan for p in parameters}
            record.update({f"{p}_se": np.nan for p in parameters})
            record.update(loglik=np.nan, aic=np.nan, n_obs=0, converged=False, iterations=0, message=None,
                          error=row.get("error"))
            if fit is not None:
                estimate = fit.params["estimate"].reindex(parameters).to_numpy(dtype=float)
                se = fit.params["std_error"].reindex(parameters).to_numpy(dtype=float)
                record.update(zip(parameters, estimate))
                record.update(zip([f"{p}_se" for p in parameters], se))
                record.update(loglik=fit.loglik, aic=fit.aic, n_obs=fit.n_obs, converged=bool(fit.converged),
                              iterations=int(fit.iterations), message=fit.message)
            records.append(record)
        index = pd.Index(names, name="dataset")
        self.table = pd.DataFrame.from_records(records, index=index)
        for column in ("message", "error"):  # None, not NaN, where there is none
            self.table[column] = pd.Series([r[column] for r in records], index=index, dtype=object)

    @property
    def failed(self) -> pd.Series:
        """The error of each data set that has no fit."""
        return self.table["error"].dropna()

    def estimates(self) -> pd.DataFrame:
        """The free parameters' estimates of the data sets that were fitted.

        Returns
        -------
        pandas.DataFrame
            One row per fitted data set, one column per free parameter.
        """
        free = [p for p in self.model.parameter_names if not self._fixed(p)]
        return self.table.loc[self.table["error"].isna(), free]

    def _fixed(self, name: str) -> bool:
        p = self.model.parameters.get(name)
        return p is not None and p.fixed

    def summary(self) -> str:
        """How many data sets were fitted and converged, and the spread of each estimate across them.

        Returns
        -------
        str
            The summary's text.
        """
        t = self.table
        fitted = int(t["error"].isna().sum())
        lines = [f"fleet of {len(t)} data sets of model {self.model.name}: {fitted} fitted, "
                 f"{int(t['converged'].sum())} converged, {len(t) - fitted} failed"]
        estimates = self.estimates()
        if len(estimates):
            q = estimates.quantile([0.0, 0.25, 0.5, 0.75, 1.0]).T
            q.columns = ["min", "25%", "median", "75%", "max"]
            lines.append(q.to_string(float_format=lambda v: f"{v:.5g}"))
        for _name, error in self.failed.items():
            lines.append(f"  {error}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()

    def plot(self, parameters=None, bins: int = 20):
        """Histograms of the estimates across the fleet, one panel per free parameter.

        Parameters
        ----------
        parameters : sequence of str, optional
            The parameters to show (default: every free parameter).
        bins : int
            Histogram bins.

        Returns
        -------
        matplotlib.figure.Figure
            The figure (tick labels in a compact number format).
        """
        from matplotlib.figure import Figure
        from matplotlib.ticker import MaxNLocator, ScalarFormatter

        estimates = self.estimates()
        names = list(estimates.columns) if parameters is None else list(parameters)
        cols = min(3, max(len(names), 1))
        rows = -(-len(names) // cols)
        fig = Figure(figsize=(4 * cols, 3 * rows), layout="constrained")
        axes = fig.subplots(rows, cols, squeeze=False)
        for ax, name in zip(axes.flat, names):
            ax.hist(estimates[name].dropna(), bins=bins, color="tab:blue", alpha=0.8)
            ax.xaxis.set_major_locator(MaxNLocator(nbins=4))
            formatter = ScalarFormatter(useMathText=True)
            formatter.set_powerlimits((-2, 3))
            ax.xaxis.set_major_formatter(formatter)
            ax.tick_params(labelsize=8)
            ax.set_xlabel(name)
            ax.set_ylabel("data sets")
        for ax in list(axes.flat)[len(names):]:
            ax.set_visible(False)
        fig.suptitle(f"{self.model.name}: estimates across {len(estimates)} data sets")
        return fig
