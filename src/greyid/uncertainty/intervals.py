"""Prediction and simulation intervals that carry the parameters' uncertainty too.

A prediction at fixed θ̂ has the state and measurement noise only.  Drawing
θ_j from the Laplace approximation (Gaussian in the optimiser's coordinates z,
so every draw respects the bounds; the covariance is the fit's, mapped to z) or
from posterior draws of [`sample()`][greyid.uncertainty.sampling.sample], the predictive distribution
is the mixture of the Gaussian predictions N(ŷ_j, S_j): its mean is the average
of ŷ_j, its variance E[S_j] + Var[ŷ_j] (law of total variance), and its interval
ends are the mixture's quantiles (by bisection on the mixture's distribution
function).  Simulation intervals are quantiles over paths simulated with a
different θ_j each.
"""

from __future__ import annotations


import numpy as np
import pandas as pd
from scipy import special

from ..errors import ModelError, warn
from ..estimate.calls import simulate_at
from ..estimate.results import FitWarning, check_level
from ..estimate.transforms import Transform


def parameter_draws(fit, draws: int = 200, seed: int = 0, posterior=None) -> np.ndarray:
    """Parameter vectors drawn with the fit's uncertainty.

    Parameters
    ----------
    fit : FitResult
        The fit.
    draws : int
        The number of vectors.
    seed : int
        The random seed.
    posterior : Posterior, optional
        Resample its draws (seeded) instead of drawing from the Laplace approximation in z.

    Returns
    -------
    numpy.ndarray
        (draws, parameters), all parameters in the model's order; those without a
        standard error (at a bound, fixed) stay at their estimates, with a warning
        for free ones.
    """
    if not isinstance(draws, (int, np.integer)) or draws < 2:
        raise ModelError(f"draws must be an integer of at least 2, got {draws!r}")
    names = list(fit.model.parameter_names)
    estimate = fit.params.loc[names, "estimate"].to_numpy(dtype=np.float64)
    rng = np.random.default_rng(seed)
    out = np.tile(estimate, (draws, 1))
    if posterior is not None:
        rows = rng.integers(0, len(posterior.draws), draws)
        for name in posterior.draws.columns:
            out[:, names.index(name)] = posterior.draws[name].to_numpy()[rows]
        return out
    cov = fit.cov
    usable = [n for n in cov.index if np.isfinite(cov.loc[n, n]) and cov.loc[n, n] > 0]
    missing = [n for n in cov.index if n not in usable]
    if missing:
        warn(f"{fit.model.name}: {', '.join(missing)} ha{'s' if len(missing) == 1 else 've'} no standard "
                      "error (at a bound or not determined); held at the estimate in the parameter draws",
                      FitWarning)
    if not usable:
        return out
    rows = fit.params.loc[usable]
    transform = Transform.from_bounds([None if np.isnan(v) else v for v in rows["lower_bound"]],
                                      [None if np.isnan(v) else v for v in rows["upper_bound"]])
    z_hat = transform.to_z(rows["estimate"].to_numpy(dtype=np.float64))
    slope = transform.derivative(z_hat)
    cov_z = cov.loc[usable, usable].to_numpy() / np.outer(slope, slope)
    w, V = np.linalg.eigh(0.5 * (cov_z + cov_z.T))
    root = V * np.sqrt(np.clip(w, 0.0, None))
    z = z_hat + rng.standard_normal((draws, len(usable))) @ root.T
    theta = np.asarray(transform.to_theta(z, np))
    for j, name in enumerate(usable):
        out[:, names.index(name)] = theta[:, j]
    return out


def mixture_quantiles(means: np.ndarray, sds: np.ndarray, probabilities, iterations: int = 60) -> np.ndarray:
    """Quantiles of equal-weight mixtures of normals: ``means``, ``sds`` (draws, points) → (len(p), points)."""
    means, sds = np.asarray(means, dtype=np.float64), np.maximum(np.asarray(sds, dtype=np.float64), 1e-300)
    out = []
    for p in np.atleast_1d(probabilities):
        lo = (means - 12 * sds).min(axis=0)
        hi = (means + 12 * sds).max(axis=0)
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            below = special.ndtr((mid - means) / sds).mean(axis=0) < p
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
        out.append(0.5 * (lo + hi))
    return np.array(out)


def predict(fit, data=None, steps: int = 1, interval: float = 0.95, draws: int = 200, seed: int = 0,
            posterior=None) -> pd.DataFrame:
    """Predictions ``steps`` samples ahead with intervals that include the parameters' uncertainty.

    Parameters
    ----------
    fit : FitResult
        The fit.
    data : pandas.DataFrame, optional
        Other data (default: the fit's); rows of future inputs with missing outputs forecast.
    steps : int
        The horizon in samples.
    interval : float
        The level of the central interval.
    draws : int
        Parameter vectors drawn (Laplace approximation, or ``posterior``).
    seed : int
        Their random seed.
    posterior : Posterior, optional
        Draws from ``fit.sample()`` to use instead of the Laplace approximation.

    Returns
    -------
    pandas.DataFrame
        The time column; per output its mean, ``<y>_sd`` (the total standard
        deviation), ``<y>_lower`` and ``<y>_upper`` (the mixture's central
        interval) and ``<y>_sd_noise`` (at θ̂ alone, as ``fit.predict``).
    """
    from ..filters.api import predict_draws

    check_level(interval)
    frame = fit._data(data)
    if isinstance(frame, list):
        raise ModelError("prediction intervals take one data set; pass data= for the one to predict")
    model = fit.model
    thetas = parameter_draws(fit, draws, seed, posterior)
    names = list(model.parameter_names)
    at_estimate = fit.params.loc[names, "estimate"].to_numpy(dtype=np.float64)
    series, means, covs = predict_draws(model, np.vstack([at_estimate, thetas]), frame, steps=steps,
                                        **fit._filtering_settings())
    sds = np.sqrt(np.clip(np.diagonal(covs, axis1=2, axis2=3), 0.0, None))  # (1 + draws, N, outputs)
    tail = (1 - interval) / 2
    columns = {series.time_name: frame[series.time_name].to_numpy()}
    for j, name in enumerate(model.output_names):
        m, s = means[1:, :, j], sds[1:, :, j]
        lower, upper = mixture_quantiles(m, s, [tail, 1 - tail])
        columns[name] = m.mean(axis=0)
        columns[f"{name}_sd"] = np.sqrt((s ** 2).mean(axis=0) + m.var(axis=0))
        columns[f"{name}_lower"] = lower
        columns[f"{name}_upper"] = upper
        columns[f"{name}_sd_noise"] = sds[0, :, j]
    return pd.DataFrame(columns, index=series.index)


def simulate(fit, data=None, n_paths: int = 200, interval: float = 0.95, seed: int = 0, posterior=None,
             parameter_uncertainty: bool = True, method: str = "euler", **options) -> pd.DataFrame:
    """Quantile bands of simulated outputs, each path with its own parameter draw (or all at θ̂).

    Parameters
    ----------
    fit : FitResult
        The fit.
    data : pandas.DataFrame, optional
        Times and inputs (default: the fit's data).
    n_paths : int
        The number of paths.
    interval : float
        The level of the central band.
    seed : int
        The random seed.
    posterior : Posterior, optional
        Draws from ``fit.sample()`` to use instead of the Laplace approximation.
    parameter_uncertainty : bool
        A parameter draw per path (False: every path at θ̂).
    method : {"euler", "milstein", "heun", "exact"}
        The integration scheme.
    **options
        ``substeps``, ``calculus``, ``noise`` (see ``Model.simulate``).

    Returns
    -------
    pandas.DataFrame
        The time column; per output the mean over paths and ``<y>_lower``,
        ``<y>_upper`` (the central band of the paths).
    """
    check_level(interval)
    if not isinstance(n_paths, (int, np.integer)) or n_paths < 2:
        raise ModelError(f"n_paths must be an integer of at least 2, got {n_paths!r}")
    frame = fit._data(data)
    if isinstance(frame, list):
        frame = frame[0]
    model = fit.model
    names = list(model.parameter_names)
    settings = dict(hold=fit.settings["hold"], time=fit.settings["time"], method=method, **options)
    if parameter_uncertainty:
        thetas = parameter_draws(fit, n_paths, seed, posterior)
        outputs = np.concatenate([simulate_at(model, dict(zip(names, theta)), frame, n_paths=1, seed=seed + 1 + k,
                                              **settings).outputs for k, theta in enumerate(thetas)])
        times = frame[fit.settings["time"]].to_numpy()
    else:
        simulation = simulate_at(model, fit.values, frame, n_paths=n_paths, seed=seed, **settings)
        outputs, times = simulation.outputs, frame[fit.settings["time"]].to_numpy()
    tail = (1 - interval) / 2
    columns = {fit.settings["time"]: times}
    for j, name in enumerate(model.output_names):
        columns[name] = outputs[:, :, j].mean(axis=0)
        columns[f"{name}_lower"] = np.quantile(outputs[:, :, j], tail, axis=0)
        columns[f"{name}_upper"] = np.quantile(outputs[:, :, j], 1 - tail, axis=0)
    return pd.DataFrame(columns, index=frame.index)


def plot_intervals(table: pd.DataFrame, data: pd.DataFrame | None = None, title: str | None = None):
    """A figure of a prediction or simulation table: the mean, the band and the measured outputs.

    Parameters
    ----------
    table : pandas.DataFrame
        A [`predict()`][greyid.uncertainty.intervals.predict] or
        [`simulate()`][greyid.uncertainty.intervals.simulate] table: the outputs
        are the columns with ``_lower`` and ``_upper`` companions, the time its first column.
    data : pandas.DataFrame, optional
        The measured outputs (rows aligned with the table's), drawn as dots.
    title : str, optional
        The figure's title.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    from ..validation.plots import band_figure

    time_name = table.columns[0]
    outputs = [c[:-len("_lower")] for c in table.columns if c.endswith("_lower") and f"{c[:-6]}_upper" in table]
    if not outputs:
        raise ModelError("the table has no <output>_lower/<output>_upper columns; make it with interval= or "
                         "parameter_uncertainty=True")
    frame = pd.DataFrame({time_name: table[time_name]}, index=table.index)
    for name in outputs:
        measured = data[name] if data is not None and name in data else np.nan
        frame[name] = measured
        frame[f"{name}_simulated"] = table[name]
        frame[f"{name}_lower"], frame[f"{name}_upper"] = table[f"{name}_lower"], table[f"{name}_upper"]
    return band_figure(frame, time_name, outputs, title or "outputs with their intervals", "interval",
                       centre_label="mean")
