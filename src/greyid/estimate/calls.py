"""A model's calls at given parameters, with the settings resolved as the model's methods resolve them.

A call's settings are those given, else the model's own (its model file's ``[data]``
and ``[filter]``, or ``set_options``); the data's columns are renamed to the model's
names and text times are read (``ModelSpec.call_settings``).  Then the filter, the
smoother, the k-step predictor, the criterion or the simulator runs.  ``greyid.Model``'s
methods and every layer that needs these calls at the estimates (results, intervals,
validation, design, studies) use these functions.
"""

from __future__ import annotations

from ..filters.api import filter_data, laplace_residuals, predict_data, smooth_data
from ..model.options import DATA_KEYS, FILTER_KEYS
from ..simulate.simulate import simulate
from .criteria import loglik

#: The settings a simulation takes from the model (its other settings are its own arguments).
SIMULATION_KEYS = ("time", "hold", "time_unit", "columns")


def filter_at(model, params, data, **given):
    """[`Model.filter()`][greyid.api.Model.filter]: the filter through ``data`` at ``params``."""
    data, settings = model.call_settings(data, given, DATA_KEYS + FILTER_KEYS)
    return filter_data(model, params, data, **settings)


def laplace_residuals_at(model, params, data, **given):
    """The Laplace method's one-step-ahead quantile residuals at ``params``
    ([`laplace_residuals()`][greyid.filters.api.laplace_residuals])."""
    data, settings = model.call_settings(data, given, DATA_KEYS + FILTER_KEYS)
    return laplace_residuals(model, params, data, **settings)


def smooth_at(model, params, data, **given):
    """[`Model.smooth()`][greyid.api.Model.smooth]: smoothed states at ``params``."""
    data, settings = model.call_settings(data, given, DATA_KEYS + FILTER_KEYS)
    return smooth_data(model, params, data, **settings)


def predict_at(model, params, data, steps: int = 1, states: bool = False, **given):
    """[`Model.predict()`][greyid.api.Model.predict]: ``steps``-ahead predictions at ``params``."""
    data, settings = model.call_settings(data, given, DATA_KEYS + FILTER_KEYS)
    return predict_data(model, params, data, steps=steps, states=states, **settings)


def loglik_at(model, params, data, **given) -> float:
    """[`Model.loglik()`][greyid.api.Model.loglik]: the log-likelihood (3.18) at ``params``."""
    data, settings = model.call_settings(data, given, DATA_KEYS + FILTER_KEYS)
    return loglik(model, params, data, **settings)


def simulate_at(model, params, data_or_times, n_paths: int = 1, method: str = "euler", seed: int = 0, **options):
    """[`Model.simulate()`][greyid.api.Model.simulate]: sample paths at ``params``."""
    data_or_times, settings = model.call_settings(data_or_times, options, SIMULATION_KEYS)
    return simulate(model, params, data_or_times, n_paths=n_paths, method=method, seed=seed, **settings)
