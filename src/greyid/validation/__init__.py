"""Model validation (thesis chapter 5).

Residual tests work on any residual series (arrays or pandas Series; NaN values
are dropped, see `greyid.validation.series`); structure tests work on
fits.  ``fit.validate()`` runs the residual tests on a fit and plots them.
"""

from .bayes import BayesComparison, log_marginal_likelihood, posterior_odds
from .bispectral import Bispectrum, bispectrum, gaussianity_test, linearity_test
from .independence import acf, difference_sign_test, ks_normality, ljung_box, pacf, rank_test, turning_point_test
from .plots import coherency_figure, residual_dashboard
from .selection import ForwardSelection, select_forward
from .series import TestResult
from .simulation import ParameterBootstrap, SimulationCheck, parameter_bootstrap, simulation_check
from .spectral import (Coherency, coherency, coherency_test, cross_correlation, cumulative_periodogram,
                       cumulative_periodogram_test, input_correlation_test, periodogram)
from .structure import (approximation_test, compare_fits, cross_validation_test, fpe, lm_test, lr_test,
                        simulated_datasets, wald_test)
from .validate import Validation, validate

__all__ = [
    "TestResult", "acf", "pacf", "ljung_box", "turning_point_test", "difference_sign_test", "rank_test",
    "ks_normality", "periodogram", "cumulative_periodogram", "cumulative_periodogram_test", "cross_correlation",
    "input_correlation_test", "Coherency", "coherency", "coherency_test", "Bispectrum", "bispectrum",
    "gaussianity_test", "linearity_test", "lr_test", "wald_test", "lm_test", "cross_validation_test",
    "approximation_test", "simulated_datasets", "compare_fits", "fpe", "select_forward", "ForwardSelection",
    "posterior_odds", "log_marginal_likelihood", "BayesComparison", "simulation_check", "parameter_bootstrap",
    "SimulationCheck", "ParameterBootstrap", "validate", "Validation", "residual_dashboard", "coherency_figure",
]
