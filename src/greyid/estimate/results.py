"""The result of a fit: estimates, honest uncertainty, and what to do next.

Modelled on statsmodels' results: ``params``, ``bse``, ``cov``, ``corr``,
``loglik``, ``aic``, ``bic``, ``summary()``.  Standard errors come from the
exact Hessian of the negative log-posterior at the optimum (section 3.3.2);
when that Hessian is singular or indefinite the ill-determined directions are
reported by parameter name instead of dropping parameters.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping, Self

import numpy as np
import pandas as pd
from scipy import special

from ..data.files import named_dataset, read_data
from ..data.prepare import as_frames
from ..errors import DataError, FitWarning, ModelError  # noqa: F401  (FitWarning: re-exported)
from ..model.equations import parse_expression
from ..model.options import rename_columns
from ..model.parameters import tests_against_zero
from ..model.units import derived_unit, pretty
from ..outputs import complete_generation, write_atomic
from ..schema import FIT_FORMAT, check_fit_document
from .calls import filter_at, laplace_residuals_at, predict_at, simulate_at, smooth_at
from .settings import FitSettings, filter_settings


#: A Laplace fit's filter() and predict() run the particle filter with this many particles (where its value is not
#: the exact Kalman filter's likelihood).
LAPLACE_FILTER_PARTICLES = 1000


def p_value_text(p: float) -> str:
    """A p-value as the summary and the report print it: 3 digits, or ``< 1e-16`` below double
    precision's resolution of 1 − p (where a computed 0 means "below that", not zero)."""
    return "< 1e-16" if p < 1e-16 else f"{p:.3g}"


@dataclass
class Estimates:
    """The numbers of a fit: estimates and their uncertainty for one model fitted to one or more data sets.

    What the estimator gives; users get it as a [`FitResult`][greyid.api.FitResult] (whose attributes
    these are), which adds what the layers above make of it: profiles, sampling, prediction
    intervals, validation, reports.
    """

    model: object
    params: pd.DataFrame
    cov: pd.DataFrame
    loglik: float
    criterion_value: float
    n_obs: int
    converged: bool
    message: str
    iterations: int
    settings: FitSettings
    warnings: list = field(default_factory=list)
    ill_determined: list = field(default_factory=list)
    data: list | None = None
    start_values: list = field(default_factory=list)
    starts: list = field(default_factory=list)  # per start: label, criterion, converged, iterations, message
    data_file: str | None = None  # where the data came from: a file's path, or dataset:NAME (greyid.datasets)
    _cache: dict = field(default_factory=dict, repr=False)

    # -------------------------------------------------------------- numbers
    @property
    def values(self) -> dict[str, float]:
        """Estimates of all parameters (free and fixed) by name."""
        return {k: float(v) for k, v in self.params["estimate"].items()}

    @property
    def bse(self) -> pd.Series:
        """Standard errors of the estimates (NaN for fixed parameters)."""
        return self.params["std_error"]

    @property
    def n_params(self) -> int:
        """Number of estimated parameters."""
        return int((~self.params["fixed"]).sum())

    @property
    def corr(self) -> pd.DataFrame:
        """The correlation matrix of the free parameters' estimates."""
        sd = np.sqrt(np.diag(self.cov.to_numpy()))
        return self.cov / np.outer(sd, sd)

    @property
    def llf(self) -> float:
        """The Gaussian log-likelihood at the estimates (statsmodels' name for ``loglik``)."""
        return self.loglik

    @property
    def nobs(self) -> int:
        """Number of observed output values (statsmodels' name for ``n_obs``)."""
        return self.n_obs

    @property
    def tests_against_zero(self) -> dict:
        """Per parameter, whether its t- and p-value (a test against 0) mean anything: not for a
        log-parameter nor a parameter of the initial state only (the summary and report leave them out)."""
        return tests_against_zero(self.model)

    @property
    def tvalues(self) -> pd.Series:
        """Estimates over standard errors (NaN for fixed parameters)."""
        return self.params["t_value"]

    @property
    def pvalues(self) -> pd.Series:
        """Two-sided p-values of the t-values (Student t, N − k degrees of freedom)."""
        return self.params["p_value"]

    @property
    def cov_type(self) -> str:
        """How ``cov`` was computed: ``"hessian"``, ``"opg"`` or ``"sandwich"`` (see `covariance`)."""
        return self.settings.get("cov_type", "hessian")

    def cov_params(self) -> pd.DataFrame:
        """The covariance matrix of the free parameters' estimates.

        Returns
        -------
        pandas.DataFrame
            A copy of ``cov``.
        """
        return self.cov.copy()

    @property
    def df_resid(self) -> int:
        """Degrees of freedom of the t-values: observations less free parameters (at least 1)."""
        return max(self.n_obs - self.n_params, 1)

    def conf_int(self, level: float = 0.95, method: str = "wald") -> pd.DataFrame:
        """Wald confidence intervals: estimate ± the Student-t quantile (N − k degrees of freedom) × the
        standard error, NaN where there is none.

        Parameters
        ----------
        level : float
            The confidence level, between 0 and 1.
        method : {"wald"}
            Profile-likelihood intervals are [`FitResult.conf_int()`][greyid.api.FitResult.conf_int]'s.

        Returns
        -------
        pandas.DataFrame
            Columns ``lower`` and ``upper``, one row per parameter.
        """
        if method not in ("wald", "profile"):
            raise ModelError(f"confidence intervals by method {method!r} are not available; "
                             "use method='wald' or 'profile'")
        if not 0 < level < 1:
            raise ModelError(f"level must lie between 0 and 1, got {level!r}")
        if method == "profile":
            raise ModelError("profile intervals are taken by greyid.FitResult.conf_int (or "
                             "greyid.uncertainty.profile_intervals(fit, level)); these estimates have Wald intervals")
        q = float(special.stdtrit(self.df_resid, 0.5 + level / 2))
        est, se = self.params["estimate"], self.params["std_error"]
        return pd.DataFrame({"lower": est - q * se, "upper": est + q * se}, index=self.params.index)

    @property
    def aic(self) -> float:
        """Akaike's information criterion, −2 log L + 2k (5.7)."""
        return -2.0 * self.loglik + 2.0 * self.n_params

    @property
    def bic(self) -> float:
        """Bayesian information criterion, −2 log L + k log N (5.8)."""
        return -2.0 * self.loglik + self.n_params * math.log(self.n_obs)

    @property
    def hqic(self) -> float:
        """Hannan–Quinn information criterion, −2 log L + 2k log log N."""
        return -2.0 * self.loglik + 2.0 * self.n_params * math.log(math.log(max(self.n_obs, 3)))

    # -------------------------------------------------------------- report
    def summary(self, level: float = 0.95) -> str:
        """A readable table of the fit, like statsmodels' summary.

        Parameters
        ----------
        level : float
            The confidence level of the intervals shown.

        Returns
        -------
        str
            The criterion, filter and hold, log-likelihood, information criteria,
            convergence, the parameter table with units, bounds and flags, and the warnings.
        """
        s = self.settings
        crit = s["criterion"].upper()
        if s.get("robust"):
            crit += f", robust {s['robust'][0]} (c = {s['robust'][1]:g})"
        if s.get("horizon", 1) > 1:
            crit += f", {s['horizon']}-step predictions"
        lines = [
            f"greyid fit of model '{self.model.name}' ({self.model.kind})",
            "=" * 78,
            f"criterion: {crit:32s} filter: {s['method']} ({s['form']}), hold {s['hold']}",
            f"log-likelihood: {self.loglik:<16.6f} observations: {self.n_obs:<10d} parameters: {self.n_params}",
            f"AIC: {self.aic:<16.4f} BIC: {self.bic:<16.4f} converged: {self.converged} ({self.iterations} iterations)",
            f"covariance: {self.cov_type}" + (" (the Hessian by central differences of the exact gradient)"
                                               if s.get("hessian") == "differences" else ""),
        ]
        if len(self.start_values) > 1:
            lines.append(f"starts: {self.start_spread()}")
        if s.get("substep_note"):
            lines.append(f"filter accuracy: {s['substep_note']}")
        elif self.model.kind != "lti":
            lines.append(f"filter accuracy: {s.get('substeps', 1)} sub-steps per interval (as set)")
        if s.get("robust") or s.get("horizon", 1) > 1 or s["criterion"] == "map":
            lines.append(f"criterion value (log scale): {self.criterion_value:.6f}")
        lines.append("-" * 78)
        tail = (1 - level) / 2
        lines.append(f"{'':12s} {'estimate':>13s} {'std_error':>11s} {'t_value':>9s} {'p_value':>9s} "
                     f"{f'[{tail:.3g}':>11s} {f'{1 - tail:.3g}]':>11s}")
        def fmt(v, w, p):
            return f"{v:{w}.{p}g}" if v is not None and np.isfinite(v) else " " * (w - 1) + "-"
        intervals = self.conf_int(level)
        tested = self.tests_against_zero
        for name, row in self.params.iterrows():
            flag = " fixed" if row["fixed"] else (" at bound" if row["at_bound"] else "")
            if not row["fixed"] and not row["reliable"]:
                flag += " (unreliable)"
            ci = intervals.loc[name]
            unit = f" [{pretty(row['unit'])}]" if row.get("unit") else ""
            t, p = (row["t_value"], row["p_value"]) if tested.get(name, True) else (None, None)
            shown_p = p_value_text(p) if p is not None and np.isfinite(p) else "-"
            lines.append(f"{name:12.12s} {fmt(row['estimate'], 13, 6)} {fmt(row['std_error'], 11, 4)} "
                         f"{fmt(t, 9, 4)} {shown_p:>9s} {fmt(ci['lower'], 11, 5)} "
                         f"{fmt(ci['upper'], 11, 5)}{unit}{flag}")
        if not all(tested.get(n, True) for n in self.params.index):
            lines.append("t_value, p_value: against 0; not shown for log-parameters (exp(p) in the equations) and "
                         "parameters of the initial state only, where 0 is no null value")
        bounded = self.params[self.params["lower_bound"].notna() | self.params["upper_bound"].notna()]
        if len(bounded):
            lines.append("-" * 78)
            lines.append(f"{'bounds':12s} {'lower':>13s} {'upper':>11s}")
            for name, row in bounded.iterrows():
                lines.append(f"{name:12.12s} {fmt(row['lower_bound'], 13, 6)} {fmt(row['upper_bound'], 11, 6)}"
                             f"{' at bound' if row['at_bound'] else ''}")
        lines.append("=" * 78)
        for w in self.warnings:
            lines.append(f"warning: {w}")
        return "\n".join(lines)

    def start_spread(self, tolerance: float = 0.01) -> str:
        """How many starts reached the best criterion, and the next best value.

        Parameters
        ----------
        tolerance : float
            Criterion values within this of the best count as the best.

        Returns
        -------
        str
            One line, e.g. ``"4, 2 reached the best value 5434.59; next best 5434.58 (the
            criterion has several optima)"``.
        """
        # Pruned and failed starts ended nowhere in particular: not optima of their own.
        stopped = {"pruned": 0, "failed": 0}
        ended = []
        for i, v in enumerate(self.start_values):
            message = self.starts[i].get("message", "") if i < len(self.starts) else ""
            kind = next((k for k in stopped if str(message).startswith(k)), None)
            if kind is not None:
                stopped[kind] += 1
            elif np.isfinite(v):
                ended.append(v)
        values = np.sort(np.array(ended))[::-1]
        if len(values) == 0:
            return f"{len(self.start_values)}, none finite"
        best = values[0]
        reached = int(np.sum(values >= best - tolerance))
        text = f"{len(self.start_values)}, {reached} reached the best value {best:.6g}"
        others = values[values < best - tolerance]
        if len(others):
            text += f"; next best {others[0]:.6g} (the criterion has several optima)"
        for kind, count in stopped.items():
            if count:
                text += f"; {count} {kind} (see fit.starts)"
        return text

    def __repr__(self) -> str:
        return (f"<{type(self).__name__} {self.model.name}: loglik={self.loglik:.4f}, k={self.n_params}, "
                f"converged={self.converged}>")

    # -------------------------------------------------------------- derived quantities
    def derived(self, expressions: Mapping[str, str] | None = None) -> pd.DataFrame:
        """Functions of the parameters with delta-method standard errors (6.35).

        Parameters
        ----------
        expressions : mapping of str to str, optional
            ``{name: expression in the parameters}`` (default: the quantities declared
            on the model with ``add_derived`` or a model file's ``[derived]``).

        Returns
        -------
        pandas.DataFrame
            ``estimate`` and ``std_error`` per quantity (and ``unit`` where the model has units).

        Raises
        ------
        ModelError
            An expression that uses a name that is not a parameter.
        """
        if expressions is None:
            expressions = self.model.derived
        import sympy as sp

        names = list(self.params.index)
        free = ~self.params["fixed"].to_numpy()
        theta = self.params["estimate"].to_numpy(dtype=np.float64)
        cov = self.cov.to_numpy()
        symbols = [parse_expression(n, "parameter") for n in names]
        rows = {}
        for label, text in expressions.items():
            expr = parameter_expression(text, names, f"derived quantity '{label}'")
            # The value and exact gradient from SymPy, evaluated by NumPy: JAX would compile each
            # operation on its first use, which for a model's few quantities costs more than the evaluation.
            used = [i for i, sym in enumerate(symbols) if sym in expr.free_symbols]
            fn = sp.lambdify([symbols[i] for i in used], [expr] + [sp.diff(expr, symbols[i]) for i in used], "numpy")
            out = [float(v) for v in fn(*theta[used])]
            grad = np.zeros(len(names))
            grad[used] = out[1:]
            g = grad[free]
            # Parameters the quantity does not depend on do not enter its variance, even
            # when their own variance is unknown (NaN, e.g. at a bound).
            nonzero = g != 0
            variance = g[nonzero] @ cov[np.ix_(nonzero, nonzero)] @ g[nonzero]
            rows[label] = {"estimate": out[0], "std_error": float(np.sqrt(max(variance, 0.0)))}
        table = pd.DataFrame.from_dict(rows, orient="index", columns=["estimate", "std_error"])
        units = getattr(self.model, "units", {})
        if units:
                table["unit"] = [derived_unit(self.model, units, expressions[label], self.settings.get("time", "t"))
                             for label in table.index]
        return table

    def to_prior(self, names=None) -> dict:
        """This fit's estimates as a Gaussian prior for the next experiment (section 7.4, 3.46).

        ``model.fit(new_data, criterion="map", prior=fit.to_prior())`` carries this
        experiment's knowledge, and its uncertainty, into the next.

        Parameters
        ----------
        names : sequence of str, optional
            The parameters (default: every free parameter with a standard error).

        Returns
        -------
        dict
            ``{"mean", "sd", "corr"}``, the correlations those of the estimates.

        Raises
        ------
        ModelError
            A name that is not a free parameter, or one without a standard error.
        """
        free = list(self.cov.index)
        if names is None:
            names = [n for n in free if np.isfinite(self.cov.loc[n, n]) and self.cov.loc[n, n] > 0]
        names = list(names)
        for name in names:
            if name not in free:
                raise ModelError(f"'{name}' is not a free parameter of this fit (free: {free})")
            if not (np.isfinite(self.cov.loc[name, name]) and self.cov.loc[name, name] > 0):
                raise ModelError(f"'{name}' has no standard error (at a bound or not determined); "
                                 "it cannot carry a Gaussian prior")
        if not names:
            raise ModelError("no free parameter of this fit has a standard error to make a prior of")
        cov = self.cov.loc[names, names].to_numpy(dtype=np.float64)
        sd = np.sqrt(np.diag(cov))
        corr = cov / np.outer(sd, sd)
        return {"mean": {n: float(self.params.loc[n, "estimate"]) for n in names},
                "sd": {n: float(s) for n, s in zip(names, sd)},
                "corr": {(a, b): float(corr[i, j]) for i, a in enumerate(names) for j, b in enumerate(names)
                         if i < j and corr[i, j] != 0.0}}

    # -------------------------------------------------------------- filtering on the fitted model
    def with_data(self, data, data_file: str | None = None) -> Self:
        """This fit with data attached (e.g. to a loaded fit), so residuals and validation work.

        Parameters
        ----------
        data : pandas.DataFrame or list of pandas.DataFrame
            The data.
        data_file : str, optional
            Where they came from, kept with the fit.

        Returns
        -------
        Estimates
            A copy holding the data (of this fit's class).
        """
        frames = as_frames(rename_columns(data, self.model.options.get("columns")))
        return replace(self, data=frames, data_file=data_file if data_file is not None else self.data_file,
                       _cache={})

    def attach_stored_data(self) -> list | None:
        """The fit's data; a loaded fit reads the data file it stores (``data_file``) on first use.

        Returns
        -------
        list of pandas.DataFrame or None
            The data, or None where the fit has none and names no file.
        """
        if self.data is None and self.data_file:
            if named_dataset(self.data_file) is None and not Path(self.data_file).is_file():
                raise DataError(f"the data file this fit was made from, '{self.data_file}', is not there any "
                                "more; attach the data with fit.with_data(frame)")
            self.data = as_frames(rename_columns(read_data(self.model, self.data_file),
                                                 self.model.options.get("columns")))
        return self.data

    def _data(self, data):
        if data is not None:
            return data
        if self.attach_stored_data() is None:
            raise ModelError("this fit carries no data (it was loaded from a file without one); "
                             "pass data explicitly or attach it with fit.with_data(frame)")
        return self.data[0] if len(self.data) == 1 else self.data

    def _filter_settings(self):
        return filter_settings(self.settings)

    def _filtering_settings(self):
        """The settings of the filter behind ``filter()`` and ``predict()``: the fit's own; for a Laplace fit,
        whose method has no filter, the exact Kalman filter where the Laplace value is its likelihood (a linear
        time-invariant model with Gaussian outputs and the exact transitions,
        [`exact_kalman()`][greyid.filters.laplace.exact_kalman]), else the particle filter's
        (LAPLACE_FILTER_PARTICLES particles, the fit's seed)."""
        from ..filters.laplace import exact_kalman

        settings = self._filter_settings()
        if settings["method"] != "laplace":
            return settings
        scheme = settings.get("scheme")
        settings = {k: v for k, v in settings.items() if k not in ("scheme", "substeps")}
        if exact_kalman(self.model.structure, scheme):
            return dict(settings, method="kalman")
        return dict(settings, method="particle", particles=LAPLACE_FILTER_PARTICLES, seed=self.settings["seed"])

    def filter(self, data=None):
        """The filter run at the estimates (for a Laplace fit, which has no filter of its own, the exact Kalman filter
        where the Laplace value is its likelihood, else the particle filter: see ``_filtering_settings``).

        Parameters
        ----------
        data : pandas.DataFrame, optional
            Other data (default: the fit's).

        Returns
        -------
        FilterResult or list of FilterResult
            One per data set; its ``method`` names the filter.
        """
        return filter_at(self.model, self.values, self._data(data), **self._filtering_settings())

    def smooth(self, data=None):
        """Smoothed states at the estimates: Rauch–Tung–Striebel after the fit's filter; for a Laplace fit, the
        mode of the states with the Laplace approximation's marginal covariances.

        Parameters
        ----------
        data : pandas.DataFrame, optional
            Other data (default: the fit's).

        Returns
        -------
        SmootherResult or list of SmootherResult
            One per data set.
        """
        return smooth_at(self.model, self.values, self._data(data), **self._filter_settings())

    def predict(self, data=None, steps: int = 1, states: bool = False, interval: float | None = None):
        """Output (and state) predictions ``steps`` samples ahead at the estimates, with standard deviations (for
        a Laplace fit, the filter of ``filter()``).

        Parameters
        ----------
        data : pandas.DataFrame, optional
            Other data (default: the fit's).
        steps : int
            The horizon in samples.
        states : bool
            Also the states' predictions.
        interval : float, optional
            A level such as 0.95: adds ``<y>_lower`` and ``<y>_upper`` columns (Gaussian).

        Returns
        -------
        pandas.DataFrame or list of pandas.DataFrame
            The time column, each output and ``<output>_sd`` (and the interval's columns).
        """
        out = predict_at(self.model, self.values, self._data(data), steps=steps, states=states,
                         **self._filtering_settings())
        if interval is None:
            return out
        check_level(interval)
        q = float(special.ndtri(0.5 + interval / 2))
        for frame in (out if isinstance(out, list) else [out]):
            for name in self.model.output_names:
                frame[f"{name}_lower"] = frame[name] - q * frame[f"{name}_sd"]
                frame[f"{name}_upper"] = frame[name] + q * frame[f"{name}_sd"]
        return out

    def simulate(self, data=None, n_paths: int | None = None, seed: int = 0, method: str = "euler", **options):
        """Sample paths of the fitted model at the estimates, driven by the data's inputs.

        Parameters
        ----------
        data : pandas.DataFrame, optional
            Times and inputs (default: the fit's data).
        n_paths : int, optional
            The number of paths (default 1).
        seed : int
            The random seed.
        method : {"euler", "milstein", "heun", "exact"}
            The integration scheme.
        **options
            ``substeps``, ``calculus``, ``noise`` (see [`Model.simulate()`][greyid.api.Model.simulate]).

        Returns
        -------
        Simulation
            The paths.
        """
        d = self._data(data)
        if isinstance(d, list):
            d = d[0]
        return simulate_at(self.model, self.values, d, n_paths=1 if n_paths is None else n_paths, seed=seed,
                           method=method, hold=self.settings["hold"], time=self.settings["time"], **options)

    @property
    def residuals(self):
        """The one-step-ahead quantile residuals per output (NaN where unobserved): standard normal where the
        model is right, whatever the observations' distribution; a Gaussian filter's are its standardized
        innovations, a Laplace fit's those of ctsmTMB's one-step-ahead residuals
        ([`laplace_residuals()`][greyid.filters.api.laplace_residuals])."""
        if "residuals" not in self._cache and self.settings["method"] == "laplace":
            self._cache["residuals"] = laplace_residuals_at(self.model, self.values, self._data(None),
                                                            **self._filter_settings())
        if "residuals" not in self._cache:
            res = self.filter()

            def residuals(r):  # (a result built elsewhere may lack them: its standardized innovations)
                return r.standardized_innovations if r.quantile_residuals is None else r.quantile_residuals

            self._cache["residuals"] = [residuals(r) for r in res] if isinstance(res, list) else residuals(res)
        return self._cache["residuals"]

    # -------------------------------------------------------------- saving
    def to_dict(self) -> dict:
        """The fit as plain data (what [`save()`][greyid.api.FitResult.save] writes as JSON).

        Returns
        -------
        dict
            The model's text, the estimates, covariance, settings, warnings and starts.
        """
        def clean(v):
            if isinstance(v, (float, np.floating)):
                return None if not np.isfinite(v) else float(v)
            if isinstance(v, (np.bool_, bool)):
                return bool(v)
            return v

        def setting(key, v):
            if key == "prior" and isinstance(v, Mapping) and isinstance(v.get("corr"), Mapping):
                # Pairs as "a,b", the form model files use (schema.prior_correlation reads it back).
                v = dict(v, corr={",".join(k) if isinstance(k, tuple) else k: r for k, r in v["corr"].items()})
            if isinstance(v, np.ndarray):
                return v.tolist()
            return list(v) if isinstance(v, tuple) else v

        return {
            "format": FIT_FORMAT,
            "model": self.model.to_dict(),
            "params": {n: {k: clean(v) for k, v in row.items()} for n, row in self.params.iterrows()},
            "cov": {"names": list(self.cov.index), "matrix": self.cov.to_numpy().tolist()},
            "loglik": self.loglik,
            "criterion_value": self.criterion_value,
            "n_obs": self.n_obs,
            "converged": self.converged,
            "message": self.message,
            "iterations": self.iterations,
            "settings": {k: setting(k, v) for k, v in self.settings.items()},
            "warnings": list(self.warnings),
            "ill_determined": self.ill_determined,
            "starts": self.starts,
            "data_file": self.data_file,
        }

    def save(self, path) -> None:
        """Write the fit as JSON (model text, estimates, covariance, settings), atomically.

        A process killed meanwhile leaves the previous file whole.

        Parameters
        ----------
        path : str or pathlib.Path
            The file.
        """
        write_atomic(path, json.dumps(self.to_dict(), indent=2))


def parameter_expression(text: str, names, what: str):
    """``text`` parsed as a function of the parameters ``names`` only (else a ModelError naming ``what``)."""
    expr = parse_expression(text, what)
    extra = {s.name for s in expr.free_symbols} - set(names)
    if extra:
        raise ModelError(f"{what} uses '{sorted(extra)[0]}', which is not a parameter")
    return expr


def check_level(interval) -> None:
    """An interval's level lies strictly between 0 and 1."""
    if not 0 < interval < 1:
        raise ModelError(f"interval must lie between 0 and 1 (e.g. 0.95), got {interval!r}")


def parameter_table(model, theta, free, std_error, *, t_value=None, p_value=None, at_bound=None,
                    reliable=None, gradient=None) -> pd.DataFrame:
    """A fit's ``params`` table: one row per parameter of ``model`` (free and fixed), in its order.

    Parameters
    ----------
    model : ModelSpec
        The model (its parameters' bounds and units).
    theta : array
        Every parameter's value.
    free : sequence of int
        The positions of the free parameters; the other rows are fixed.
    std_error : array
        The free parameters' standard errors.
    t_value, p_value, gradient : array, optional
        The free parameters' t- and p-values and the criterion's gradient (NaN where not given).
    at_bound, reliable : array of bool, optional
        Per free parameter, whether it ended at a bound (default: none) and whether its standard
        error can be trusted (default: all).

    Returns
    -------
    pandas.DataFrame
        Columns ``estimate``, ``std_error``, ``t_value``, ``p_value``, ``lower_bound``, ``upper_bound``,
        ``fixed``, ``at_bound``, ``reliable``, ``gradient`` and, where the model has units, ``unit``.
    """
    from ..model.parameters import log_parametrised

    names = list(model.parameter_names)
    n_free = len(free)
    missing = np.full(n_free, np.nan)
    at_bound = np.zeros(n_free, dtype=bool) if at_bound is None else np.asarray(at_bound, dtype=bool)
    reliable = np.ones(n_free, dtype=bool) if reliable is None else np.asarray(reliable, dtype=bool)
    # The table built column by column (a row of dicts and set_index cost a millisecond a fit).
    declared = model.parameters
    position = {i: j for j, i in enumerate(free)}
    free_rows = [position.get(i) for i in range(len(names))]

    def column(values, fixed_value=np.nan):
        values = missing if values is None else values
        return np.array([fixed_value if j is None else values[j] for j in free_rows], dtype=float)

    def bound(side):
        return np.array([np.nan if declared.get(name) is None or getattr(declared[name], side) is None
                         else getattr(declared[name], side) for name in names], dtype=float)

    params = pd.DataFrame({
        "estimate": np.asarray(theta, dtype=float), "std_error": column(std_error),
        "t_value": column(t_value), "p_value": column(p_value),
        "lower_bound": bound("lower"), "upper_bound": bound("upper"),
        "fixed": np.array([j is None for j in free_rows]),
        "at_bound": np.array([j is not None and bool(at_bound[j]) for j in free_rows]),
        "reliable": np.array([j is None or bool(reliable[j]) for j in free_rows]),
        "gradient": column(gradient)}, index=pd.Index(names))
    units = getattr(model, "units", {})
    if units:
        # A log-parameter holds the logarithm of a quantity in its declared unit (exp(p11)·dω).
        logs = log_parametrised(model.structure)
        params["unit"] = [(f"log({units[name]})" if name in logs else units[name]) if units.get(name) else ""
                          for name in params.index]
    return params


def read_fit_file(path) -> dict:
    """The document of a fit file written by ``FitResult.save()`` (or ``greyid fit --out``).

    Raises
    ------
    ModelError
        A file that is missing, a folder, or not JSON.
    """
    path = Path(path)
    if path.parent.is_dir():
        complete_generation(path.parent)  # a run killed while moving its files into place
    if path.is_dir() or not path.is_file():
        raise ModelError(f"fit file '{path}' {'is a folder' if path.is_dir() else 'not found'}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ModelError(f"fit file '{path}' is not valid JSON ({err})") from None


def estimates_from_dict(spec: dict, model_class, where: str = "the fit", model=None) -> Estimates:
    """The [`Estimates`][greyid.estimate.results.Estimates] of
    [`to_dict()`][greyid.api.FitResult.to_dict]'s form; errors name ``where`` it came from.

    The document is checked first; then ``model`` (the caller's) or a ``model_class`` built from the
    stored model is attached.
    """
    check_fit_document(spec, where)
    model = model_class.from_dict(spec["model"]) if model is None else model
    params = pd.DataFrame.from_dict(spec["params"], orient="index")
    # Files written before greyid 0.2 named the bounds "lower" and "upper".
    params = params.rename(columns={"lower": "lower_bound", "upper": "upper_bound"})
    for col in ("estimate", "std_error", "t_value", "p_value", "lower_bound", "upper_bound", "gradient"):
        if col in params:
            params[col] = params[col].astype(float)
    for col in ("fixed", "at_bound", "reliable"):
        if col in params:
            params[col] = params[col].astype(bool)
    names = spec["cov"]["names"]
    cov = pd.DataFrame(np.asarray(spec["cov"]["matrix"], dtype=float).reshape(len(names), len(names)),
                       index=names, columns=names)
    settings = FitSettings.from_dict(spec["settings"], where)
    return Estimates(model=model, params=params, cov=cov, loglik=spec["loglik"],
               criterion_value=spec["criterion_value"], n_obs=spec["n_obs"], converged=spec["converged"],
               message=spec["message"], iterations=spec["iterations"], settings=settings,
               warnings=spec.get("warnings", []), ill_determined=spec.get("ill_determined", []), data=None,
               starts=spec.get("starts", []), start_values=[s["criterion"] for s in spec.get("starts", [])],
               data_file=spec.get("data_file"))
