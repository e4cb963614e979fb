"""Estimation: maximum likelihood and MAP with exact derivatives (chapter 3)."""

from .criteria import GaussianPrior, log_criterion, squared_norm
from .estimation import fit
from .results import FitResult, FitWarning, load_fit

__all__ = ["fit", "FitResult", "FitWarning", "load_fit", "GaussianPrior", "log_criterion", "squared_norm"]
