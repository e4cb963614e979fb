"""Uncertainty beyond the Hessian: profile likelihoods, posterior sampling, prediction intervals.

* `profile()` — the profile of the criterion in a parameter or derived quantity;
* [`profile_intervals()`][greyid.uncertainty.profile.profile_intervals] — likelihood-ratio confidence intervals by root
finding on profiles;
* [`plot_profile()`][greyid.uncertainty.profile.plot_profile] — a profile's deviance with the χ² threshold;
* [`sample()`][greyid.uncertainty.sampling.sample] — NUTS draws from the fit's posterior
([`Posterior`][greyid.uncertainty.sampling.Posterior]);
* [`sample_pmmh()`][greyid.uncertainty.pmmh.sample_pmmh] — particle marginal Metropolis–Hastings draws, where
  only a particle filter's estimate of the likelihood exists;
* [`predict()`][greyid.uncertainty.intervals.predict], [`simulate()`][greyid.uncertainty.intervals.simulate] —
intervals with the parameters' uncertainty too,
  [`plot_intervals()`][greyid.uncertainty.intervals.plot_intervals] their bands.
"""

from .profile import plot_profile, profile, profile_interval, profile_intervals
from .intervals import parameter_draws, plot_intervals, predict, simulate
from .sampling import Posterior, sample
from .pmmh import sample_pmmh

__all__ = ["profile", "profile_interval", "profile_intervals", "plot_profile", "sample", "sample_pmmh", "Posterior",
           "predict", "simulate", "parameter_draws", "plot_intervals"]
