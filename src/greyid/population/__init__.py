"""Population (nonlinear mixed-effects) SDE models: many data sets, shared structure, individual parameters.

[`fit_population()`][greyid.population.fit.fit_population] estimates the typical values, covariate effects and the
random effects' covariance Ω by the Laplace approximation of the marginal
likelihood ([`laplace`][greyid.population.laplace]) and returns a
[`PopulationResult`][greyid.population.result.PopulationResult].
"""

from .fit import fit_population
from .members import PopulationWarning
from .result import LikelihoodRatio, PopulationResult, likelihood_ratio, load_population

__all__ = ["fit_population", "PopulationResult", "PopulationWarning", "likelihood_ratio", "LikelihoodRatio",
           "load_population"]
