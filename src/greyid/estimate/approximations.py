"""How far a likelihood approximation is from the truth: the particle filter's estimate with its Monte
Carlo error, and every method's value side by side.

A Gaussian filter's log-likelihood of a nonlinear model is an approximation whose
error does not show from inside it.  The bootstrap particle filter
([`particle`][greyid.filters.particle]) estimates the likelihood itself, with an error
that falls as 1/√P; [`compare_methods()`][greyid.estimate.approximations.compare_methods]
puts each method's value (the Gaussian filters', the Laplace method's) beside it
and flags those that differ by more than the particle estimate's errors allow.
"""

from __future__ import annotations

from typing import NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp
import numpy as np
import pandas as pd
from scipy.special import logsumexp

from ..errors import ModelError
from ..filters.api import _prepare, filter_options
from ..filters.driver import make_replicated_filter
from ..filters.protocol import GAUSSIAN_METHODS, LAPLACE, PARTICLE
from ..model.options import DATA_KEYS, FILTER_KEYS
from ..runtime.jit import structure_program
from .criteria import loglik

#: Independent runs of the particle filter behind one estimate and its error.
REPLICATES = 8


class ParticleEstimate(NamedTuple):
    """The particle filter's log-likelihood estimate from independent runs.

    ``loglik`` is log of the runs' mean likelihood (the mean of unbiased estimates of the
    likelihood, so unbiased itself), ``std_error`` its Monte Carlo standard error (delta
    method), ``spread`` the standard deviation of one run's log-likelihood, ``runs`` each run's.
    """

    loglik: float
    std_error: float
    spread: float
    runs: np.ndarray


def particle_loglik(model, params, data, particles: int = 1000, seed: int = 0, replicates: int = REPLICATES,
                    **settings) -> ParticleEstimate:
    """The particle filter's log-likelihood at ``params`` with its Monte Carlo standard error.

    Parameters
    ----------
    model : greyid.Model
        The model.
    params : dict or array
        The parameters' values.
    data : pandas.DataFrame or list of pandas.DataFrame
        The data.
    particles : int
        Particles of each run.
    seed : int
        The seed the runs' random numbers are split from.
    replicates : int
        Independent runs (at least 2 for an error), vectorised in one program.
    **settings
        ``time``, ``hold``, ``time_unit``, ``substeps``, ``resample``, ``proposal`` as for ``model.loglik``.

    Returns
    -------
    ParticleEstimate
        The estimate, its standard error, the spread of one run and each run's value.

    Raises
    ------
    ModelError
        Fewer than 2 replicates, or settings the particle filter does not take.

    Examples
    --------
    >>> from greyid.estimate.approximations import particle_loglik
    >>> estimate = particle_loglik(model, params, data, particles=2000)  # doctest: +SKIP
    >>> estimate.loglik, estimate.std_error                             # doctest: +SKIP
    """
    if not isinstance(replicates, int) or replicates < 2:
        raise ModelError(f"replicates must be an integer of at least 2 for a standard error, got {replicates!r}")
    data, settings = model.call_settings(data, settings, DATA_KEYS + FILTER_KEYS)
    settings.pop("method", None)
    place = {k: settings.pop(k) for k in ("time", "hold", "time_unit") if k in settings}
    structure, theta, prepared = _prepare(model, params, data, place.get("time", "t"), place.get("hold", "zoh"),
                                          place.get("time_unit"))
    options = filter_options(structure, PARTICLE, particles=particles, seed=seed, **settings)
    program = structure_program(structure, ("replicated", options, replicates),
                                lambda: make_replicated_filter(structure, options, replicates))
    runs = sum(np.asarray(program(jnp.asarray(theta), inputs)) for _, inputs in prepared)
    estimate = float(logsumexp(runs) - np.log(replicates))
    relative = np.exp(runs - runs.max())
    std_error = float(np.std(relative, ddof=1) / np.sqrt(replicates) / np.mean(relative))
    return ParticleEstimate(estimate, std_error, float(np.std(runs, ddof=1)), runs)


def compare_methods(model, params, data, methods=None, particles: int = 1000, seed: int = 0,
                    replicates: int = REPLICATES, **settings) -> pd.DataFrame:
    """Every method's log-likelihood at ``params`` beside the particle filter's estimate.

    Parameters
    ----------
    model : greyid.Model
        The model.
    params : dict or array
        The parameters' values (a fit's estimates).
    data : pandas.DataFrame or list of pandas.DataFrame
        The data.
    methods : sequence of str, optional
        The methods to compare with the particle filter (default: every Gaussian filter and the
        Laplace method where the observations are normal, the Laplace method otherwise).
    particles, seed, replicates : int
        The particle filter's reference (see [`particle_loglik()`][greyid.estimate.approximations.particle_loglik]).
    **settings
        ``time``, ``hold``, ``time_unit``, ``substeps`` as for ``model.loglik``; ``resample`` and ``proposal``
        for the particle filter's runs.

    Returns
    -------
    pandas.DataFrame
        One row per method: ``loglik``, ``std_error`` (the particle filter's; 0 for the deterministic
        filters), ``difference`` from the particle estimate and ``agrees`` (within 3 standard errors,
        and 0.1 at least).

    Raises
    ------
    ModelError
        A method that is not a filter greyid has.
    """
    reference = particle_loglik(model, params, data, particles, seed, replicates, **settings)
    gaussian = not model.structure.distributions
    known = (*GAUSSIAN_METHODS, LAPLACE)
    chosen = list(methods) if methods is not None else (list(known) if gaussian else [LAPLACE])
    rows = {}
    for method in chosen:
        if method not in known:
            raise ModelError(f"unknown method {method!r} to compare; use some of {list(known)}")
        rows[method] = (loglik(model, params, data, method=method,
                               **{k: v for k, v in settings.items() if k not in ("resample", "proposal")}), 0.0)
    rows[PARTICLE] = (reference.loglik, reference.std_error)
    table = pd.DataFrame.from_dict(rows, orient="index", columns=["loglik", "std_error"])
    table.index.name = "method"
    table["difference"] = table["loglik"] - reference.loglik
    allowed = max(3 * reference.std_error, 0.1)
    table["agrees"] = table["difference"].abs() <= allowed
    return table


__all__ = ["ParticleEstimate", "particle_loglik", "compare_methods", "REPLICATES"]
