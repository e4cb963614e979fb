"""Measured against simulated output, and a parametric bootstrap of the parameters (5.3).

* The deterministic part of the fitted model, driven by the measured inputs
  from the initial mean, shows whether the model catches the dynamics; a Monte
  Carlo of the full SDE gives the band its sample paths fill.
* The parametric bootstrap samples parameters from their asymptotic normal
  distribution N(θ̂, Σ̂) and simulates the deterministic part for each: how
  robust the simulated outputs are to the parameters' uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..errors import ModelError
from ..estimate.calls import simulate_at


@dataclass(frozen=True)
class SimulationCheck:
    """Per output: measured, deterministic simulation and the Monte Carlo band, with summaries."""

    frame: pd.DataFrame  # time, <y>, <y>_simulated, <y>_lower, <y>_upper, <y>_mean per output
    rmse: dict  # output → root mean square of measured − simulated
    coverage: dict  # output → fraction of measurements inside the band
    level: float
    time_name: str
    output_names: tuple


@dataclass(frozen=True)
class ParameterBootstrap:
    """Parameter samples and the band of deterministic simulations they give."""

    samples: pd.DataFrame  # one row per accepted sample
    frame: pd.DataFrame  # time, <y>, <y>_simulated (at θ̂), <y>_lower, <y>_upper
    rejected: int  # samples outside the parameters' bounds, drawn again
    level: float
    time_name: str
    output_names: tuple


def _frame_of(fit, data):
    frames = fit._data(data)
    return frames[0] if isinstance(frames, list) else frames


def _exact(fit, noise: bool = False) -> bool:
    """Whether the model's paths (without ``noise``: its deterministic path) are simulated exactly."""
    structure = fit.model.structure
    # Without noise a transformed state follows dx = f dt, which is not the transformed linear drift: Heun.
    return structure.is_linear and not (structure.ode_drift is not None and not noise)


def _simulate(fit, params, data, **options):
    s = fit.settings
    method = options.pop("method", None) or ("exact" if _exact(fit, options.get("noise", True)) else "heun")
    return simulate_at(fit.model, params, data, method=method, hold=s["hold"], time=s["time"],
                       time_unit=s.get("time_unit"), **options)


def simulation_check(fit, data=None, n_paths: int = 200, seed: int = 0, level: float = 0.05,
                     substeps: int = 20) -> SimulationCheck:
    """The deterministic simulation and a Monte Carlo band of ``n_paths`` paths against the measurements.

    Parameters
    ----------
    fit : FitResult
        The fit.
    data : pandas.DataFrame, optional
        Other data (default: the fit's).
    n_paths : int
        Simulated paths.
    seed : int
        Their random seed.
    level : float
        The band's significance level.
    substeps : int
        Integration steps per sampling interval.

    Returns
    -------
    SimulationCheck
        ``frame`` (per output: measured, simulated, the band and the paths' mean),
        ``rmse`` and ``coverage`` (the fraction of measurements inside the band) per output.
    """
    frame = _frame_of(fit, data)
    outputs = fit.model.output_names
    mc = _simulate(fit, fit.values, frame, n_paths=n_paths, seed=seed, substeps=substeps)
    # A linear model's paths, with noise or without, come from one program: the deterministic path as
    # many times as the band's paths (all equal) compiles nothing more; a nonlinear one's ODE is another.
    det = _simulate(fit, fit.values, frame, noise=False, substeps=substeps,
                    n_paths=n_paths if _exact(fit) else 1)
    time_name = fit.settings["time"]
    out = pd.DataFrame({time_name: frame[time_name].to_numpy()}, index=frame.index)
    rmse, coverage = {}, {}
    for j, name in enumerate(outputs):
        y = frame[name].to_numpy(dtype=np.float64)
        out[name] = y
        out[f"{name}_simulated"] = det.outputs[0, :, j]
        out[f"{name}_mean"] = mc.outputs[:, :, j].mean(axis=0)
        lo, hi = np.quantile(mc.outputs[:, :, j], [level / 2, 1 - level / 2], axis=0)
        out[f"{name}_lower"], out[f"{name}_upper"] = lo, hi
        seen = ~np.isnan(y)
        rmse[name] = float(np.sqrt(np.mean((y[seen] - det.outputs[0, seen, j]) ** 2)))
        coverage[name] = float(np.mean((y[seen] >= lo[seen]) & (y[seen] <= hi[seen])))
    return SimulationCheck(out, rmse, coverage, level, time_name, tuple(outputs))


def parameter_bootstrap(fit, data=None, n_samples: int = 100, seed: int = 0, level: float = 0.05,
                        substeps: int = 20) -> ParameterBootstrap:
    """Deterministic simulations at draws from N(θ̂, Σ̂) (draws outside the bounds redrawn).

    Parameters
    ----------
    fit : FitResult
        The fit.
    data : pandas.DataFrame, optional
        Other data (default: the fit's).
    n_samples : int
        Parameter draws.
    seed : int
        Their random seed.
    level : float
        The band's significance level.
    substeps : int
        Integration steps per sampling interval.

    Returns
    -------
    ParameterBootstrap
        ``samples`` (the accepted draws), ``frame`` (per output: measured, simulated at
        θ̂ and the band) and ``rejected`` (draws outside the bounds, drawn again).
    """
    frame = _frame_of(fit, data)
    free = list(fit.cov.index)
    cov = fit.cov.to_numpy()
    if not np.all(np.isfinite(cov)):
        raise ModelError("some parameters have no covariance (at a bound or not determined); "
                         "the parametric bootstrap needs all of them")
    mean = fit.params.loc[free, "estimate"].to_numpy(dtype=np.float64)
    lower = fit.params.loc[free, "lower_bound"].to_numpy(dtype=np.float64)
    upper = fit.params.loc[free, "upper_bound"].to_numpy(dtype=np.float64)
    lower, upper = np.where(np.isnan(lower), -np.inf, lower), np.where(np.isnan(upper), np.inf, upper)
    rng = np.random.default_rng(seed)
    chol = np.linalg.cholesky(0.5 * (cov + cov.T) + 1e-300 * np.eye(len(free)))
    accepted, rejected = [], 0
    while len(accepted) < n_samples:
        draw = mean + chol @ rng.standard_normal(len(free))
        if np.all((draw > lower) & (draw < upper)):
            accepted.append(draw)
        else:
            rejected += 1
            if rejected > 100 * n_samples:
                raise ModelError("almost every draw from N(θ̂, Σ̂) falls outside the parameters' bounds")
    samples = pd.DataFrame(accepted, columns=free)
    outputs = fit.model.output_names
    sims = []
    for _, row in samples.iterrows():
        params = dict(fit.values, **row.to_dict())
        sims.append(_simulate(fit, params, frame, noise=False, substeps=substeps).outputs[0])
    sims = np.stack(sims)  # (samples, N, outputs)
    centre = _simulate(fit, fit.values, frame, noise=False, substeps=substeps).outputs[0]
    time_name = fit.settings["time"]
    out = pd.DataFrame({time_name: frame[time_name].to_numpy()}, index=frame.index)
    for j, name in enumerate(outputs):
        out[name] = frame[name].to_numpy(dtype=np.float64)
        out[f"{name}_simulated"] = centre[:, j]
        out[f"{name}_lower"], out[f"{name}_upper"] = np.quantile(sims[:, :, j], [level / 2, 1 - level / 2], axis=0)
    return ParameterBootstrap(samples, out, rejected, level, time_name, tuple(outputs))
