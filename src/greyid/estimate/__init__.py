"""Estimation: maximum likelihood and MAP with exact derivatives (chapter 3).

The results' module (pandas tables, SciPy's distributions) loads when first used.
"""

from .criteria import GaussianPrior, log_criterion, squared_norm
from .estimation import fit

__all__ = ["fit", "Estimates", "FitWarning", "GaussianPrior", "log_criterion", "squared_norm"]


def __getattr__(name):
    if name in ("Estimates", "FitWarning"):
        from . import results

        return getattr(results, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
