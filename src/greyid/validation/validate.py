"""``fit.validate()``: every residual test of chapter 5 on a fit, in one object.

For each output (and each data set) the standardised one-step residuals go
through the independence, normality, whiteness and bispectrum tests, and
against each input through the input-correlation F test and the multiple
coherency test.  The result's ``tests`` is a DataFrame with columns
``test, output, statistic, df, p_value, reject``; it plots itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..errors import DataError, ModelError
from . import bispectral, independence, spectral
from .plots import band_figure, coherency_figure, labelled, prediction_figure, residual_dashboard

RESIDUAL_TESTS = {
    "ljung_box": lambda x, o: independence.ljung_box(x, o["lags"]),
    "turning_points": lambda x, o: independence.turning_point_test(x),
    "difference_sign": lambda x, o: independence.difference_sign_test(x),
    "rank": lambda x, o: independence.rank_test(x),
    "ks_normality": lambda x, o: independence.ks_normality(x),
    "cumulative_periodogram": lambda x, o: spectral.cumulative_periodogram_test(x),
    "bispectrum_gaussianity": lambda x, o: bispectral.gaussianity_test(x),
    "bispectrum_linearity": lambda x, o: bispectral.linearity_test(x),
}


@dataclass
class Validation:
    """The tests of one fit and what is needed to draw them."""

    fit: object = field(repr=False)
    level: float
    tests: pd.DataFrame
    residuals: dict  # label → standardised residuals (Series)
    inputs: dict  # label → inputs on the same rows (DataFrame)
    times: dict  # label → times (Series)
    skipped: list  # (test, output, reason) for tests the data could not support
    lags: int | None = None
    m: int | None = None

    @property
    def rejected(self) -> pd.DataFrame:
        """The rows of ``tests`` that reject at the level."""
        return self.tests[self.tests["reject"]]

    def summary(self) -> str:
        """How many tests reject at the level, and the table of every test.

        Returns
        -------
        str
            The summary.
        """
        lines = [f"validation of '{self.fit.model.name}' at level {self.level}: "
                 f"{int(self.tests['reject'].sum())} of {len(self.tests)} tests reject"]
        with pd.option_context("display.width", 120, "display.max_rows", 200):
            lines.append(self.tests.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
        for test, output, reason in self.skipped:
            lines.append(f"skipped {test} for {output}: {reason}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"<Validation of '{self.fit.model.name}': {int(self.tests['reject'].sum())} of "
                f"{len(self.tests)} tests reject at {self.level}>")

    def _label(self, output):
        if output is None:
            return next(iter(self.residuals))
        if output not in self.residuals:
            raise ModelError(f"no residuals named '{output}'; choose from {list(self.residuals)}")
        return output

    # -------------------------------------------------------------- figures
    def _units(self) -> dict:
        """The model's units for figures, the time axis's included where anything says it."""
        from ..model.units import figure_units

        return figure_units(self.fit.model, self.fit.settings.get("time", "t"), self.fit.settings)

    def plot(self, output: str | None = None):
        """The residual dashboard of one output.

        Parameters
        ----------
        output : str, optional
            The output (default: the first).

        Returns
        -------
        matplotlib.figure.Figure
            The figure (never shown; save it or display it in a notebook).
        """
        label = self._label(output)
        time_name = self.fit.settings.get("time", "t")
        return residual_dashboard(self.residuals[label], self.inputs[label], self.times[label], self.lags,
                                  self.level, title=f"standardised residuals of {label}",
                                  time_label=labelled(time_name, self._units()))

    def plot_coherency(self, output: str | None = None):
        """The coherency of one output's residuals with each input, and the multiple coherency.

        Parameters
        ----------
        output : str, optional
            The output (default: the first).

        Returns
        -------
        matplotlib.figure.Figure
            The figure (never shown; save it or display it in a notebook).
        """
        label = self._label(output)
        if self.inputs[label].shape[1] == 0:
            raise ModelError("the model has no inputs; there is no coherency to draw")
        t = self.times[label].to_numpy(dtype=float)
        dt = float(np.median(np.diff(t))) if len(t) > 1 and np.issubdtype(t.dtype, np.number) else 1.0
        return coherency_figure(self.residuals[label], self.inputs[label], self.m, dt, self.level,
                                self._units().get(self.fit.settings.get("time", "t")))

    def plot_simulation(self, n_paths: int = 200, seed: int = 0):
        """The measurements against the deterministic simulation and a Monte Carlo band of the SDE.

        Parameters
        ----------
        n_paths : int
            Simulated paths of the band.
        seed : int
            Their random seed.

        Returns
        -------
        matplotlib.figure.Figure
            The figure (never shown; save it or display it in a notebook).
        """
        from .simulation import simulation_check

        check = simulation_check(self.fit, n_paths=n_paths, seed=seed, level=self.level)
        return band_figure(check.frame, check.time_name, check.output_names,
                           "measured and simulated outputs", f"{1 - self.level:.0%} Monte Carlo band",
                           units=self._units())

    def plot_bootstrap(self, n_samples: int = 100, seed: int = 0):
        """Deterministic simulations at parameters drawn from N(θ̂, Σ̂).

        Parameters
        ----------
        n_samples : int
            Parameter draws.
        seed : int
            Their random seed.

        Returns
        -------
        matplotlib.figure.Figure
            The figure (never shown; save it or display it in a notebook).
        """
        from .simulation import parameter_bootstrap

        boot = parameter_bootstrap(self.fit, n_samples=n_samples, seed=seed, level=self.level)
        return band_figure(boot.frame, boot.time_name, boot.output_names,
                           "simulated outputs under parameter uncertainty", f"{1 - self.level:.0%} bootstrap band",
                           units=self._units())

    def plot_prediction(self, steps: int = 1):
        """The measurements against ``steps``-ahead predictions with ±2 standard deviations.

        Parameters
        ----------
        steps : int
            The horizon in samples.

        Returns
        -------
        matplotlib.figure.Figure
            The figure (never shown; save it or display it in a notebook).
        """
        data = self.fit._data(None)
        data = data[0] if isinstance(data, list) else data
        pred = self.fit.predict(data, steps=steps)
        return prediction_figure(data, pred, self.fit.settings["time"], self.fit.model.output_names, steps,
                                 units=self._units())


def validate(fit, level: float = 0.05, lags: int | None = None, m: int | None = None) -> Validation:
    """The residual tests of chapter 5 on every output of a fit.

    Parameters
    ----------
    fit : FitResult
        The fit (with its data).
    level : float
        The tests' significance level, between 0 and 1.
    lags : int, optional
        Lags of the autocorrelation tests (default: from the series' length).
    m : int, optional
        The smoothing of the spectral estimates (default: from the series' length).

    Returns
    -------
    Validation
        ``tests`` (test, output, statistic, df, p_value, reject), ``rejected``,
        ``summary()`` and the plots.

    Raises
    ------
    ModelError
        A level outside (0, 1), or a fit that carries no data.
    """
    if not 0 < level < 1:
        raise ModelError(f"level must lie between 0 and 1, got {level}")
    if fit.attach_stored_data() is None:
        raise ModelError("this fit carries no data (it was loaded from a file); validation needs its residuals")
    residuals = fit.residuals
    residuals = residuals if isinstance(residuals, list) else [residuals]
    input_names = list(fit.model.input_names)
    time_name = fit.settings["time"]
    rows, skipped, res_by, in_by, t_by = [], [], {}, {}, {}
    options = {"lags": lags}
    for i, (frame, res) in enumerate(zip(fit.data, residuals)):
        for name in res.columns:
            label = name if len(residuals) == 1 else f"{name} [data {i}]"
            series = res[name].rename(label)
            res_by[label], in_by[label], t_by[label] = series, frame[input_names], frame[time_name]
            for test, run in RESIDUAL_TESTS.items():
                try:
                    rows.append((test, label, run(series, options)))
                except DataError as err:
                    skipped.append((test, label, str(err)))
            for u in input_names:
                try:
                    rows.append((f"input_correlation[{u}]", label,
                                 spectral.input_correlation_test(series, frame[u], lags)))
                except DataError as err:
                    skipped.append((f"input_correlation[{u}]", label, str(err)))
            if input_names:
                try:
                    rows.append(("coherency", label, spectral.coherency_test(series, frame[input_names], m)))
                except (DataError, np.linalg.LinAlgError) as err:
                    skipped.append(("coherency", label, str(err)))
    tests = pd.DataFrame([dict(test=t, output=o, statistic=r.statistic, df=r.df, p_value=r.p_value,
                               reject=r.reject(level)) for t, o, r in rows],
                         columns=["test", "output", "statistic", "df", "p_value", "reject"])
    return Validation(fit, level, tests, res_by, in_by, t_by, skipped, lags, m)
