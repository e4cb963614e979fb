"""Uncertainty beyond the Hessian: profile likelihoods, posterior sampling, prediction intervals.

* :func:`profile` — the profile of the criterion in a parameter or derived quantity;
* :func:`profile_intervals` — likelihood-ratio confidence intervals by root finding on profiles;
* :func:`plot_profile` — a profile's deviance with the χ² threshold;
* :func:`sample` — NUTS draws from the fit's posterior (:class:`Posterior`).
"""

from .profile import plot_profile, profile, profile_interval, profile_intervals
from .sampling import Posterior, sample

__all__ = ["profile", "profile_interval", "profile_intervals", "plot_profile", "sample", "Posterior"]
