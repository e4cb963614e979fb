"""Public entry points: log-likelihood, filtering and smoothing of DataFrames.

Data are checked, turned into arrays and padded to a length bucket (eight
buckets per doubling) so that a compiled filter is reused across data sets of
similar length; padded rows carry no observation and an interval of length 0,
so they change nothing.
"""

from __future__ import annotations

import math
from dataclasses import replace

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from scipy.special import ndtri

from ..runtime.jit import structure_program
from ..data.prepare import Series, as_frames, prepare_series
from ..errors import DataError, FilterWarning, ModelError, warn
from ..model.structure import Structure
from ..model.transforms import to_original
from .accuracy import choose_substeps, chooses_substeps
from .driver import checked_horizon, filter_steps, make_ahead, make_filter
from .gaussian import initial_state
from ..model.distributions import NORMAL, check_method, check_observed
from . import laplace
from .protocol import EKF, KALMAN, LAPLACE, PARTICLE, STOCHASTIC, FilterInputs, FilterOptions
from .delays import check_delays, delay_slots, with_delayed_inputs
from .diffuse import head_rows, scan_head
from .diffuse_smoother import make_diffuse_smoother
from .result import FilterResult, SmootherResult
from .smoother import rts_smooth

HOLDS = {"zoh": 0.0, "foh": 1.0}


def bucket(n: int, minimum: int = 16) -> int:
    """Padded size for n: a multiple of 1/8 of the largest power of two below n."""
    if n <= minimum:
        return minimum
    step = max(2 ** (int(math.floor(math.log2(n))) - 3), 1)
    return int(math.ceil(n / step) * step)


def interval_slots(n: int) -> int:
    """Padded count of a series' distinct sampling intervals (0, the first row's, among them).

    A regular series has two, kept as they are: every slot costs a step of the loop that
    discretizes them (``benchmarks/likelihood.py``); more are padded to 4 and then as rows are."""
    return 2 if n <= 2 else bucket(n, 4)


def _round_significant(values: np.ndarray, digits: int = 12) -> np.ndarray:
    """Round to ``digits`` significant digits so equal sampling intervals share one discretization."""
    out = np.zeros_like(values)
    nz = values != 0
    exponent = np.floor(np.log10(np.abs(values[nz])))
    scale = 10.0 ** (exponent - digits + 1)
    out[nz] = np.round(values[nz] / scale) * scale
    return out


def sampling_intervals(dt: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The intervals with those equal up to the rounding of the times themselves made equal.

    Times k·Δ stored in floating point give intervals that differ in their last
    digits (1e-12 relative at 10⁴ samples of 1/3 h, more further on); each
    distinct interval costs a discretization, and a long regular series is only
    recognised as regular ([`steady`][greyid.filters.steady]) once they are one.  Intervals within
    64 ulps of the largest time of each other form one value, the most frequent
    among them; a group spread wider than that (steadily varying intervals) is
    left as it is, rounded to 12 significant digits.
    """
    rounded = _round_significant(dt)
    scale = float(np.max(np.abs(times))) if len(times) else 0.0
    resolution = 64 * np.finfo(np.float64).eps * max(scale, np.max(np.abs(dt), initial=0.0))
    values, inverse, counts = np.unique(rounded, return_inverse=True, return_counts=True)
    if len(values) < 2 or resolution == 0:
        return rounded
    representative = values.copy()
    for group in np.split(np.arange(len(values)), np.flatnonzero(np.diff(values) > resolution) + 1):
        if len(group) > 1 and values[group[-1]] - values[group[0]] <= 4 * resolution and values[group[0]] > 0:
            representative[group] = values[group[np.argmax(counts[group])]]
    return representative[inverse.reshape(-1)]


def filter_inputs(series: Series, hold: str, on_device: bool = True, diffuse: tuple = ()) -> FilterInputs:
    """Arrays for the filter from a checked series (padded, see module doc).

    With ``on_device=False`` the arrays stay NumPy arrays (a fleet stacks them first); ``diffuse`` holds, for
    each diffuse initial state, the outputs that see it: the arrays mark the diffuse period
    ([`head_rows()`][greyid.filters.diffuse.head_rows]).
    """
    if hold not in HOLDS:
        raise DataError(f"unknown hold '{hold}'; use 'zoh' (inputs held) or 'foh' (inputs interpolated)")
    n_rows = series.n_rows
    size = bucket(n_rows)
    pad = size - n_rows
    t = np.concatenate([series.times, np.full(pad, series.times[-1])])
    dt = np.concatenate([[0.0], np.diff(t)])
    t_prev = np.concatenate([t[:1], t[:-1]])
    u = np.concatenate([series.inputs, np.repeat(series.inputs[-1:], pad, axis=0)])
    u_prev = np.concatenate([u[:1], u[:-1]])
    y = np.concatenate([series.outputs, np.full((pad, series.outputs.shape[1]), np.nan)])
    mask = ~np.isnan(y)
    unique, index = np.unique(sampling_intervals(dt, t), return_inverse=True)
    unique = np.concatenate([unique, np.zeros(interval_slots(len(unique)) - len(unique))])
    first = series.times[1] - series.times[0] if n_rows > 1 else 0.0
    # Every array is made in NumPy with its final dtype and transferred as it is:
    # jnp.asarray would compile a small program per shape, which a first fit waits for.
    arrays = dict(t=t, t_prev=t_prev, dt=dt, u_prev=u_prev, u_cur=u, y=np.where(mask, y, 0.0),
                  mask=mask.astype(np.float64), dt_index=index.reshape(-1).astype(np.int32), unique_dt=unique,
                  first_interval=np.float64(first), foh=np.float64(HOLDS[hold]),
                  delay_slots=np.zeros(delay_slots(series.times, regular=np.count_nonzero(unique) == 1)),
                  diffuse_rows=np.zeros(head_rows(mask, n_rows, diffuse)))
    arrays = {name: np.asarray(a) for name, a in arrays.items()}
    # One transfer for all of them (one by one, a tenth of a shorter series' compiled fit).
    return FilterInputs(**(jax.device_put(arrays) if on_device else arrays))


def padded_inputs(inputs: FilterInputs, length: int, unique: int, slots: int, head: int) -> FilterInputs:
    """``inputs`` (NumPy arrays) padded to ``length`` rows, ``unique`` sampling-interval slots, ``slots``
    delay cuts and a diffuse period of ``head`` rows.

    Padding rows repeat the last time and input, carry no observation and an interval of length 0 (as
    [`filter_inputs()`][greyid.filters.api.filter_inputs] pads), so they change nothing; nor does a longer
    diffuse period than the series' own (once P∞ is zero its steps are ordinary).
    """
    extra = length - len(inputs.t)
    if extra < 0:
        raise ValueError(f"cannot pad {len(inputs.t)} rows to {length}")
    zero = int(np.flatnonzero(inputs.unique_dt == 0.0)[0])
    last, last_input = inputs.t[-1], inputs.u_cur[-1:]
    return type(inputs)(
        t=np.concatenate([inputs.t, np.full(extra, last)]),
        t_prev=np.concatenate([inputs.t_prev, np.full(extra, last)]),
        dt=np.concatenate([inputs.dt, np.zeros(extra)]),
        u_prev=np.concatenate([inputs.u_prev, np.repeat(last_input, extra, axis=0)]),
        u_cur=np.concatenate([inputs.u_cur, np.repeat(last_input, extra, axis=0)]),
        y=np.concatenate([inputs.y, np.zeros((extra, inputs.y.shape[1]))]),
        mask=np.concatenate([inputs.mask, np.zeros((extra, inputs.mask.shape[1]))]),
        dt_index=np.concatenate([inputs.dt_index, np.full(extra, zero, dtype=inputs.dt_index.dtype)]),
        unique_dt=np.concatenate([inputs.unique_dt, np.zeros(unique - len(inputs.unique_dt))]),
        first_interval=inputs.first_interval, foh=inputs.foh, delay_slots=np.zeros(slots),
        diffuse_rows=np.zeros(head))


def shared_lengths(prepared: list) -> list:
    """The data sets of one evaluation, ``[(series, filter inputs), ...]``, padded to shared shapes where that
    pads little: the longest data set left leads a group that every other of more than half its rows joins;
    the group's data sets take its rows and its most sampling-interval slots
    ([`padded_inputs()`][greyid.filters.api.padded_inputs]).

    Data sets of one shape run through one vectorised filter (a fit's criterion sums them so, (3.18)), so a
    fit to several series of different lengths traces and compiles its filter once instead of once per
    length, and runs them side by side.  Data sets whose delay or diffuse arrays differ in shape stay apart.
    """
    if len(prepared) < 2:
        return list(prepared)
    on_device = isinstance(prepared[0][1].t, jax.Array)
    host = [jax.device_get(inputs) for _, inputs in prepared]
    order = sorted(range(len(host)), key=lambda i: -len(host[i].t))
    out = list(prepared)
    while order:
        lead = host[order[0]]
        length = len(lead.t)
        group = [i for i in order if 2 * len(host[i].t) > length and host[i].delay_slots.shape == lead.delay_slots.shape
                 and host[i].diffuse_rows.shape == lead.diffuse_rows.shape]
        order = [i for i in order if i not in group]
        unique = max(len(host[i].unique_dt) for i in group)
        for i in group:
            if len(group) > 1 and (len(host[i].t), len(host[i].unique_dt)) != (length, unique):
                padded = padded_inputs(host[i], length, unique, len(lead.delay_slots), len(lead.diffuse_rows))
                out[i] = (out[i][0], jax.device_put(padded) if on_device else padded)
    return out


#: Euler–Maruyama steps per sampling interval of the particle and ensemble filters where ``substeps`` is not given
#: (a model that is not linear and time-invariant; such a model's transition is sampled exactly).
PARTICLE_SUBSTEPS = 8


def filter_options(structure: Structure, method: str | None, **options) -> FilterOptions:
    """Settings with the default method: exact Kalman for linear models, EKF otherwise.

    Raises
    ------
    ModelError
        An unknown option, or a Gaussian filter for outputs whose distribution is not normal.
    """
    if method is None:
        method = KALMAN if structure.is_linear else EKF
    unknown = set(options) - {"form", "substeps", "iterations", "alpha", "beta", "kappa", "steady_state",
                              "particles", "seed", "resample", "scheme", "inflation",
                              "proposal"}
    if unknown:
        raise ModelError(f"unknown filter option '{sorted(unknown)[0]}'")
    if method in STOCHASTIC and options.get("substeps") is None:
        options = dict(options, substeps=PARTICLE_SUBSTEPS)
    if options.get("scheme") == "ctsmtmb" and options.get("substeps") is None:  # one step per interval
        options = dict(options, substeps=1)
    check_method(structure.distributions, structure.output_names, method)
    return FilterOptions(method=method, **{k: v for k, v in options.items() if v is not None})


def accurate_options(structure: Structure, theta, prepared, method, **options):
    """``(FilterOptions, SubstepChoice or None)``: with ``substeps`` unset, as many as accuracy needs.

    See [`accuracy`][greyid.filters.accuracy]; the choice is made on the log-likelihood at ``theta``.
    """
    if options.get("substeps") is not None or not chooses_substeps(structure, method, options.get("scheme")):
        return filter_options(structure, method, **options), None
    rest = {k: v for k, v in options.items() if k != "substeps"}
    theta = jnp.asarray(theta)

    def loglik_at(substeps):
        run = compiled_filter(structure, filter_options(structure, method, substeps=substeps, **rest), False)
        return float(sum(jnp.sum(run(theta, inputs)[0].loglik) for _, inputs in prepared))

    choice = choose_substeps(loglik_at)
    return filter_options(structure, method, substeps=choice.substeps, **rest), choice


def compiled_filter(structure: Structure, options: FilterOptions, keep_outputs: bool | str):
    """The jitted filter for these settings, compiled once per model structure."""
    return structure_program(structure, ("filter", options, keep_outputs),
                             lambda: make_filter(structure, options, keep_outputs))


def check_at_parameters(structure: Structure, theta: np.ndarray, series: Series, data: FilterInputs) -> None:
    """Errors that depend on parameter values: negative variances, a bad P0, a delay out of range."""
    check_delays(structure, theta, series.times)
    def checks(theta, data):
        data = with_delayed_inputs(structure, theta, data)
        x0, P0 = initial_state(structure, theta, data)
        S = jax.vmap(lambda u, t: structure.observation_variance(x0, u, t, theta))(data.u_cur, data.t)
        full = structure.observation_covariance
        S_full = None if full is None else jax.vmap(lambda u, t: full(x0, u, t, theta))(data.u_cur, data.t)
        return S, P0, S_full

    S, P0, S_full = structure_program(structure, ("checks",), lambda: checks)(jnp.asarray(theta), data)
    if structure.initial_covariance.diffuse:
        check_diffuse_period(structure, theta, data)
    S = np.asarray(S)[: series.n_rows]
    bad = np.argwhere(~(S > 0))
    if len(bad):
        row, j = bad[0]
        raise ModelError(
            f"the variance of observation '{structure.output_names[j]}' is {S[row, j]} at row {row} "
            "for the given parameters; variances must be positive"
        )
    if S_full is not None:
        lowest = np.linalg.eigvalsh(np.asarray(S_full)[: series.n_rows]).min(axis=1)
        bad = np.flatnonzero(~(lowest > 0))
        if len(bad):
            raise ModelError(f"the observation covariance is not positive definite at row {bad[0]} for the given "
                             f"parameters (smallest eigenvalue {lowest[bad[0]]:.4g})")
    P0 = np.asarray(P0)
    if np.all(np.isfinite(P0)) and np.abs(P0 - P0.T).max(initial=0.0) > 1e-12 * max(np.abs(P0).max(initial=0.0),
                                                                                   1e-300):
        i, j = np.unravel_index(np.argmax(np.abs(P0 - P0.T)), P0.shape)
        raise ModelError(f"the initial state covariance is not symmetric for the given parameters: element "
                         f"({i + 1}, {j + 1}) is {P0[i, j]:.6g} but ({j + 1}, {i + 1}) is {P0[j, i]:.6g}")
    # Semi-definite is allowed: a state known exactly at t₀ has variance 0.
    if not np.all(np.isfinite(P0)) or np.min(np.linalg.eigvalsh(0.5 * (P0 + P0.T))) < -1e-10 * max(
            np.abs(P0).max(), 1e-300):
        raise ModelError(
            "the initial state covariance is not positive semi-definite for the given parameters "
            f"(kind '{structure.initial_covariance.kind}'); give a positive semi-definite matrix"
        )


def check_diffuse_period(structure: Structure, theta: np.ndarray, data: FilterInputs) -> None:
    """Name the diffuse states the outputs of the diffuse period's rows do not determine (P∞ not zero at
    its end, [`head_rows()`][greyid.filters.diffuse.head_rows])."""
    def remaining(theta, data):
        parts = filter_steps(structure, FilterOptions(KALMAN))(theta, data)
        rows = jax.tree_util.tree_map(lambda a: a[:parts.diffuse.rows], parts.rows)
        state, _, _ = scan_head(parts.diffuse, parts.initial, parts.predict, rows, None, lambda terms: 0.0)
        return state.mean

    mean = structure_program(structure, ("diffuse period",), lambda: remaining)(jnp.asarray(theta), data)
    if not np.all(np.isfinite(np.asarray(mean))):
        names = [structure.state_names[i] for i in structure.initial_covariance.diffuse]
        raise ModelError(f"the diffuse initial states {names} are not all determined by the outputs of the first "
                         f"{data.diffuse_rows.shape[0]} rows (up to observation {len(names)} of the outputs that "
                         "see them) at the given parameters: an output must depend on each of them there; give "
                         "them a mean and a covariance instead")


def check_equations_finite(structure: Structure, theta: np.ndarray, series: Series, data: FilterInputs) -> None:
    """Name the equation and row where the model's functions are not finite at the initial state.

    Called where a fit's criterion is not finite at its start, to say why: an equation
    that is infinite at a time or an input value of the data (``1/t``, ``log(t)`` at
    t = 0) cannot be mended by any parameter value, and the message says so.
    """
    def values(theta, data):
        data = with_delayed_inputs(structure, theta, data)
        x0, _ = initial_state(structure, theta, data)
        at = jax.vmap(lambda u, t: (structure.drift(x0, u, t, theta), structure.diffusion(x0, u, t, theta),
                                    structure.observation(x0, u, t, theta)))
        return x0, at(data.u_cur, data.t)

    x0, (f, G, h) = structure_program(structure, ("equations finite",), lambda: values)(jnp.asarray(theta), data)
    rows = series.n_rows
    states, outputs = structure.state_names, structure.output_names
    # Each kind of equation with the name of the equation its rows belong to (G's rows are the states').
    named = [("drift", f, [f"d{x}" for x in states]), ("diffusion", G, [f"d{x}" for x in states]),
             ("observation", h, list(outputs))]
    for what, array, equations in named:
        array = np.asarray(array)[:rows]
        bad = np.argwhere(~np.isfinite(array.reshape(rows, -1)))
        if not len(bad):
            continue
        row, flat = bad[0]
        equation = equations[np.unravel_index(flat, array.shape[1:])[0]]
        matrix = structure.equations.get(what)
        expression = list(matrix)[flat] if matrix is not None and len(list(matrix)) == array[0].size else None
        text = str(expression) if expression is not None else "its expression"
        t = float(np.asarray(data.t)[row])
        where = {"t": t, **{n: float(np.asarray(data.u_cur)[row, j]) for j, n in enumerate(structure.input_names)}}
        shown = ", ".join(f"{n} = {v:.6g}" for n, v in where.items())
        hopeless = _infinite_whatever_the_parameters(expression, where, dict(zip(states, np.asarray(x0))))
        cause = ("; it is infinite there whatever the parameters' values (an expression such as 1/t or log(t) "
                 "at t = 0): shift the time column, leave that row out or change the equation") if hopeless else (
            "; check the equation and the initial parameter values")
        raise ModelError(f"the {what} of '{equation}' ({text}) is not finite at row {row} of the data "
                         f"({shown}; states at their initial values){cause}")


def _infinite_whatever_the_parameters(expression, where: dict, states: dict) -> bool:
    """Whether ``expression`` with the row's time, inputs and initial states put in is infinite or
    undefined for every value of the parameters (SymPy's ``zoo``, ``oo``, ``nan``)."""
    if expression is None:
        return False
    import sympy as sp

    given = {**where, **states}
    # The model's symbols carry assumptions (real=True): match them by name.
    values = {symbol: sp.Float(given[symbol.name]) if given[symbol.name] != 0 else sp.Integer(0)
              for symbol in expression.free_symbols if symbol.name in given}
    try:
        reduced = expression.subs(values)
    except (TypeError, ValueError):
        return False
    return bool(reduced.has(sp.zoo, sp.oo, -sp.oo, sp.nan))


def prepare_datasets(structure: Structure, theta: np.ndarray, data, time, hold, time_unit, check: bool = True,
                     on_device: bool = True):
    """Check every data set against the model (and, with ``check``, at θ); ``[(series, filter inputs), ...]``."""
    prepared = []
    for df in as_frames(data):
        series = prepare_series(df, structure.input_names, structure.output_names, time, time_unit)
        for family, name, values in zip(structure.distributions, structure.output_names, series.outputs.T):
            check_observed(family, name, values, series.times, series.time_name)
        spec = structure.initial_covariance
        inputs = filter_inputs(series, hold, on_device, spec.seen_by or ((),) * len(spec.diffuse))
        if structure.initial_covariance.kind == "process" and series.n_rows < 2:
            raise DataError(f"the data have one row (t = {series.times[0]:g}): the model's initial covariance "
                            "\"process\" is the process noise over the first sampling interval, and one row has "
                            "no interval; give the data of at least two times (or an initial covariance matrix)")
        if check:
            check_at_parameters(structure, theta, series, inputs)
        prepared.append((series, inputs))
    return prepared


def _prepare(model, params, data, time, hold, time_unit):
    structure = model.structure
    theta = model.parameter_vector(params)
    return structure, theta, prepare_datasets(structure, theta, data, time, hold, time_unit)


def _result(structure: Structure, method: str, series: Series, terms, outputs) -> FilterResult:
    n = series.n_rows
    cut = jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], outputs)
    loglik_terms = np.asarray(terms.loglik)[:n]
    idx = series.index
    states, outs = list(structure.state_names), list(structure.output_names)
    observed = ~np.isnan(series.outputs)
    innovations = np.where(observed, cut.innovation, np.nan)
    R = np.array(cut.innovation_cov)
    both = observed[:, :, None] & observed[:, None, :]
    R[~both] = np.nan
    return FilterResult(
        method=method,
        times=pd.Series(series.times, index=idx, name=series.time_name),
        predicted=pd.DataFrame(cut.predicted_mean, index=idx, columns=states),
        predicted_cov=cut.predicted_cov,
        filtered=pd.DataFrame(cut.filtered_mean, index=idx, columns=states),
        filtered_cov=cut.filtered_cov,
        output_predictions=pd.DataFrame(cut.output_prediction, index=idx, columns=outs),
        innovations=pd.DataFrame(innovations, index=idx, columns=outs),
        innovation_cov=R,
        loglik_terms=pd.Series(loglik_terms, index=idx, name="loglik"),
        transitions=cut.transition,
        guarded=_guarded(method, series, np.asarray(cut.guarded) > 0),
        quantile_residuals=_quantile_residuals(method, cut.pit, innovations, R, idx, outs),
    )


def _quantile_residuals(method: str, pit, innovations, R, index, outputs) -> pd.DataFrame:
    """Each output's one-step-ahead quantile residual Φ⁻¹(u_k): from the particle filter's probability integral
    transforms; for the Gaussian filters and the ensemble Kalman filter, whose predictive law of y_k is
    N(ŷ, R_k), Φ⁻¹(Φ(ε_k,i / √R_k,ii)) = the standardized innovation itself."""
    observed = ~np.isnan(innovations)
    if method != PARTICLE:
        sd = np.sqrt(np.diagonal(R, axis1=1, axis2=2))
        return pd.DataFrame(np.where(observed, innovations / np.where(observed, sd, 1.0), np.nan), index=index,
                            columns=outputs)
    from scipy.stats import norm

    u = np.clip(np.asarray(pit), 1e-300, 1 - 1e-16)
    return pd.DataFrame(np.where(observed, norm.ppf(u), np.nan), index=index, columns=outputs)


def _guarded(method: str, series: Series, guarded: np.ndarray) -> pd.Series:
    """The rows whose update was guarded, with a warning that names the first."""
    if guarded.any():
        first = int(np.flatnonzero(guarded)[0])
        warn(f"filter '{method}': at {int(guarded.sum())} row(s), first row {first} "
             f"({series.time_name} = {series.times[first]:g}), the measurement update's covariance "
             "P − K R Kᵀ was not positive semi-definite (the approximation's moments are "
             "inconsistent there); the Joseph form replaced it", FilterWarning)
    return pd.Series(guarded, index=series.index, name="guarded")


def _filtered(model, params, data, time, hold, method, time_unit, options):
    """``(structure, θ, results)``: the filter's results in its own coordinates (those of the transformed
    states, where any are)."""
    structure, theta, prepared = _prepare(model, params, data, time, hold, time_unit)
    opts = accurate_options(structure, theta, prepared, method, **options)[0]
    run = compiled_filter(structure, opts, keep_outputs=True)
    return structure, theta, [_result(structure, opts.method, series, *run(jnp.asarray(theta), inputs))
                       for series, inputs in prepared]


def _frame_to_original(structure: Structure, theta, frame: pd.DataFrame, cov: np.ndarray):
    mean, cov = to_original(structure.state_transforms, theta, frame.to_numpy(), cov)
    return pd.DataFrame(mean, index=frame.index, columns=frame.columns), cov


def _forces(structure: Structure, frame: pd.DataFrame, cov: np.ndarray) -> pd.DataFrame | None:
    if not structure.latent_forces:
        return None
    columns = {}
    for force in structure.latent_forces:
        mean, variance = force.values(frame.to_numpy(), cov)
        columns[force.name], columns[f"{force.name}_sd"] = mean, np.sqrt(np.maximum(variance, 0.0))
    return pd.DataFrame(columns, index=frame.index)


def in_user_coordinates(structure: Structure, theta, result):
    """A [`FilterResult`][greyid.filters.result.FilterResult] or
    [`SmootherResult`][greyid.filters.result.SmootherResult] with its states in the user's coordinates, where the
    model transforms any ([`to_original`][greyid.model.transforms.to_original]), and its latent forces' values
    where it has any; unchanged otherwise."""
    if result is None or not (structure.state_transforms or structure.latent_forces):
        return result
    if isinstance(result, SmootherResult):
        smoothed, smoothed_cov = _frame_to_original(structure, theta, result.smoothed, result.smoothed_cov)
        return replace(result, smoothed=smoothed, smoothed_cov=smoothed_cov,
                       filter_result=in_user_coordinates(structure, theta, result.filter_result),
                       latent_forces=_forces(structure, result.smoothed, result.smoothed_cov))
    predicted, predicted_cov = _frame_to_original(structure, theta, result.predicted, result.predicted_cov)
    filtered, filtered_cov = _frame_to_original(structure, theta, result.filtered, result.filtered_cov)
    return replace(result, predicted=predicted, predicted_cov=predicted_cov, filtered=filtered,
                   filtered_cov=filtered_cov, latent_forces=_forces(structure, result.filtered, result.filtered_cov))


def filter_data(model, params, data, time="t", hold="zoh", method=None, time_unit=None, **options):
    """Filter result(s): one `FilterResult`, or a list for a list of data sets; states in the user's
    coordinates."""
    structure, theta, results = _filtered(model, params, data, time, hold, method, time_unit, options)
    results = [in_user_coordinates(structure, theta, r) for r in results]
    return results[0] if isinstance(data, pd.DataFrame) else results


#: The one-step-ahead residuals of the Laplace method (TMB's ``oneStepPredict`` methods by these names).
ONE_STEP = ("gaussian", "cdf")


def one_step_method(structure: Structure, one_step: str | None) -> str:
    """The one-step method ``laplace_residuals`` runs: ``one_step``, checked, or where None "gaussian" for a linear
    model with Gaussian outputs (where the Gaussian predictive is exact) and "cdf" otherwise (where it is not, the
    tails by Laplace's method are closer to the exact transforms: docs/guide/filters.md)."""
    if one_step is None:
        return "gaussian" if laplace.linear_gaussian(structure) else "cdf"
    others = [name for name, family in zip(structure.output_names, structure.output_families) if family != NORMAL]
    if one_step not in ONE_STEP:
        raise ModelError(f"one_step={one_step!r} is not a one-step method; use one of {', '.join(map(repr, ONE_STEP))}")
    if one_step == "gaussian" and others:
        raise ModelError(f"one_step='gaussian' takes Gaussian outputs only; {', '.join(map(repr, others))} "
                         "is not: use one_step='cdf'")
    return one_step


def laplace_residuals(model, params, data, time="t", hold="zoh", time_unit=None, seed=0, one_step=None,
                      **options):
    """The Laplace method's one-step-ahead residuals per output, as ctsmTMB's.

    ``one_step="gaussian"`` (TMB's ``oneStepPredict`` method "oneStepGaussian", what ctsmTMB runs): each output
    standardized by its one-step Gaussian predictive, the mode and curvature of the joint density of the states
    and the output given the data before it, exact for a linear Gaussian model
    (``greyid.filters.laplace.one_step_gaussian``; where the joint density is Gaussian, one pass forward over the
    grid, in time linear in the series' length).  ``one_step="cdf"`` (method "cdf"):
    Φ⁻¹ of the probability integral transform, both of its tails by Laplace's method, for any model and
    distribution (``greyid.filters.laplace.one_step_transforms``).

    Parameters
    ----------
    model : greyid.Model
        The model.
    params : dict or array
        The parameters' values.
    data : pandas.DataFrame or list of pandas.DataFrame
        The data.
    time, hold, time_unit : str
        The time column, the inputs' hold (``"zoh"`` or ``"foh"``) and the unit of datetime times.
    seed : int
        Counts' transforms are randomized with ``numpy.random.default_rng([seed, i]).uniform(size=(rows,
        outputs))`` for data set i.
    one_step : {None, "gaussian", "cdf"}
        The method; None takes "gaussian" for a linear model with Gaussian outputs, else "cdf"
        (``greyid.filters.api.one_step_method``).
    **options
        The Laplace method's ``substeps`` and ``scheme`` (``method`` is ignored).

    Returns
    -------
    pandas.DataFrame or list of pandas.DataFrame
        One column per output, NaN where unobserved; standard normal where the model is right.

    Raises
    ------
    ModelError, DataError
        Settings the Laplace method does not take, a ``one_step`` that is not one of the two,
        ``one_step="gaussian"`` with an output that is not Gaussian, or data that do not fit the model.

    Examples
    --------
    >>> from greyid.filters.api import laplace_residuals
    >>> residuals = laplace_residuals(model, fit.values, data)   # doctest: +SKIP
    """
    options.pop("method", None)
    one_step = one_step_method(model.structure, one_step)
    make = laplace.one_step_gaussian if one_step == "gaussian" else laplace.one_step_transforms
    structure, theta, prepared, program = _laplace_program(
        model, params, data, time, hold, time_unit, f"one-step {one_step}", make, options)
    out = []
    for i, (series, inputs) in enumerate(prepared):
        observed = ~np.isnan(series.outputs)
        if one_step == "gaussian":
            residuals = np.asarray(program(jnp.asarray(theta), inputs))[:series.n_rows]
        else:
            uniforms = np.zeros(inputs.y.shape)
            uniforms[:series.n_rows] = np.random.default_rng([seed, i]).uniform(size=series.outputs.shape)
            u = np.asarray(program(jnp.asarray(theta), inputs, jnp.asarray(uniforms)))[:series.n_rows]
            residuals = ndtri(np.clip(u, 1e-300, 1 - 1e-16))  # Φ⁻¹ (scipy.stats.norm.ppf's own function)
        residuals = np.where(observed, residuals, np.nan)
        out.append(pd.DataFrame(residuals, index=series.index, columns=list(structure.output_names)))
    return out[0] if isinstance(data, pd.DataFrame) else out


def _laplace_program(model, params, data, time, hold, time_unit, name: str, make, options):
    """``(structure, θ, prepared data, program)``: the data prepared and ``make(structure, options)`` compiled
    once per structure and Laplace settings (sub-steps chosen as a Laplace fit chooses them)."""
    structure, theta, prepared = _prepare(model, params, data, time, hold, time_unit)
    opts = accurate_options(structure, theta, prepared, LAPLACE, **options)[0]
    return structure, theta, prepared, structure_program(structure, (name, opts), lambda: make(structure, opts))


def _laplace_smoothed(model, params, data, time, hold, time_unit, **options):
    """The Laplace method's smoothed states: the mode at the sample times, the marginals' covariances."""
    structure, theta, prepared, program = _laplace_program(
        model, params, data, time, hold, time_unit, "laplace-smoothed",
        lambda structure, opts: laplace.build(structure, opts).smoothed, options)
    out = []
    for series, inputs in prepared:
        X, P = program(jnp.asarray(theta), inputs)
        n = series.n_rows
        out.append(in_user_coordinates(structure, theta, SmootherResult(
            pd.Series(series.times, index=series.index, name=series.time_name),
            pd.DataFrame(np.asarray(X)[:n], index=series.index, columns=list(structure.state_names)),
            np.asarray(P)[:n], None)))
    return out[0] if isinstance(data, pd.DataFrame) else out


def smooth_data(model, params, data, time="t", hold="zoh", method=None, time_unit=None, **options):
    """Rauch–Tung–Striebel smoothing after any of the filters (see [`smoother`][greyid.filters.smoother]); with
    ``method="laplace"`` the Laplace method's mode and marginal covariances (its ``smoothed``)."""
    structure = model.structure
    chosen = method or (KALMAN if structure.is_linear else EKF)
    if chosen == LAPLACE:
        return _laplace_smoothed(model, params, data, time, hold, time_unit, **options)
    single = isinstance(data, pd.DataFrame)
    if structure.initial_covariance.diffuse:
        out = _diffuse_smoothed(model, params, data, time, hold, chosen, time_unit, options)
        return out[0] if single else out
    structure, theta, results = _filtered(model, params, data, time, hold, chosen, time_unit, options)
    out = []
    for res in results:
        xs, Ps = rts_smooth(jnp.asarray(res.filtered.to_numpy()), jnp.asarray(res.filtered_cov),
                            jnp.asarray(res.predicted.to_numpy()), jnp.asarray(res.predicted_cov),
                            jnp.asarray(res.transitions))
        out.append(SmootherResult(res.times, pd.DataFrame(np.asarray(xs), index=res.filtered.index,
                                                          columns=res.filtered.columns),
                                  np.asarray(Ps), res))
    out = [in_user_coordinates(structure, theta, r) for r in out]
    return out[0] if single else out


def _diffuse_smoothed(model, params, data, time, hold, method, time_unit, options) -> list:
    """Smoothing after a diffuse start ([`diffuse_smoother`][greyid.filters.diffuse_smoother]), beside the filter's
    results."""
    structure, theta, prepared = _prepare(model, params, data, time, hold, time_unit)
    opts = accurate_options(structure, theta, prepared, method, **options)[0]
    run = compiled_filter(structure, opts, keep_outputs=True)
    smoother = structure_program(structure, ("diffuse smoother", opts), lambda: make_diffuse_smoother(structure, opts))
    out = []
    for series, inputs in prepared:
        res = _result(structure, opts.method, series, *run(jnp.asarray(theta), inputs))
        means, covariances = smoother(jnp.asarray(theta), inputs)
        n = series.n_rows
        smoothed = pd.DataFrame(np.asarray(means)[:n], index=res.filtered.index, columns=res.filtered.columns)
        out.append(in_user_coordinates(structure, theta, SmootherResult(res.times, smoothed,
                                                                        np.asarray(covariances)[:n], res)))
    return out


def predict_data(model, params, data, steps=1, time="t", hold="zoh", method=None, time_unit=None,
                 states=False, **options):
    """ŷ_{k|k−steps} and its standard deviation for every output (one DataFrame per data set).

    Columns are the time column (as in the data), the outputs and ``<output>_sd``,
    and with ``states=True`` the predicted states and ``<state>_sd``; the index is
    the data's.  The prediction for row k uses the data up to row k − steps (the
    first rows are predicted from the prior).  Rows whose outputs are missing are
    predicted all the same, so rows of future inputs appended to the data give
    forecasts past its end.
    """
    steps = checked_horizon(steps)
    structure, theta, prepared = _prepare(model, params, data, time, hold, time_unit)
    opts = accurate_options(structure, theta, prepared, method, **options)[0]
    # The horizon an argument: one program predicts at every horizon (no derivative is taken here).
    program = structure_program(structure, ("ahead", opts), lambda: make_ahead(structure, opts, None))
    frames = []
    for (series, inputs), frame in zip(prepared, as_frames(data)):
        out = program(jnp.asarray(theta), inputs, jnp.asarray(steps))
        n = series.n_rows
        y = np.asarray(out.output_prediction)[:n]
        sd = np.sqrt(np.diagonal(np.asarray(out.output_cov)[:n], axis1=1, axis2=2))
        cols = {series.time_name: frame[series.time_name].to_numpy()}
        for j, name in enumerate(structure.output_names):
            cols[name] = y[:, j]
            cols[f"{name}_sd"] = sd[:, j]
        if states:
            x, x_cov = to_original(structure.state_transforms, theta, np.asarray(out.state_prediction)[:n],
                                   np.asarray(out.state_cov)[:n])
            x_sd = np.sqrt(np.diagonal(x_cov, axis1=1, axis2=2))
            for j, name in enumerate(structure.state_names):
                cols[name] = x[:, j]
                cols[f"{name}_sd"] = x_sd[:, j]
        frames.append(pd.DataFrame(cols, index=series.index))
    return frames[0] if isinstance(data, pd.DataFrame) else frames


def predict_draws(model, thetas, data, steps=1, time="t", hold="zoh", method=None, time_unit=None, **options):
    """``steps``-ahead output means (draws, N, outputs) and covariances (draws, N, outputs, outputs)
    of one data set at each parameter vector of ``thetas`` (draws, parameters), in one vectorised program."""
    steps = checked_horizon(steps)
    structure = model.structure
    thetas = np.asarray(thetas, dtype=np.float64)
    prepared = prepare_datasets(structure, thetas[0], data, time, hold, time_unit)
    opts = accurate_options(structure, thetas[0], prepared, method, **options)[0]
    program = structure_program(structure, ("ahead", opts, "draws"),
                                lambda: jax.vmap(make_ahead(structure, opts, None), in_axes=(0, None, None)))
    series, inputs = prepared[0]
    out = program(jnp.asarray(thetas), inputs, jnp.asarray(steps))
    n = series.n_rows
    return series, np.asarray(out.output_prediction)[:, :n], np.asarray(out.output_cov)[:, :n]
