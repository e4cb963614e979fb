"""Uncertainty beyond the Hessian: profile likelihoods, posterior sampling, prediction intervals.

* :func:`profile` — the profile of the criterion in a parameter or derived quantity;
* :func:`profile_intervals` — likelihood-ratio confidence intervals by root finding on profiles;
* :func:`plot_profile` — a profile's deviance with the χ² threshold;
* :func:`sample` — NUTS draws from the fit's posterior (:class:`Posterior`);
* :func:`predict`, :func:`simulate` — intervals with the parameters' uncertainty too,
  :func:`plot_intervals` their bands.
"""

from .profile import plot_profile, profile, profile_interval, profile_intervals
from .intervals import parameter_draws, plot_intervals, predict, simulate
from .sampling import Posterior, sample

__all__ = ["profile", "profile_interval", "profile_intervals", "plot_profile", "sample", "Posterior",
           "predict", "simulate", "parameter_draws", "plot_intervals"]
