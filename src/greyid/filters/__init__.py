"""Continuous–discrete filters (chapter 4, appendix A): Kalman, EKF, IEKF, UKF."""

from .core import EKF, IEKF, KALMAN, METHODS, UKF, FilterOptions
from .discretize import Discretization, discretize, stationary_covariance
from .result import FilterResult, SmootherResult

__all__ = [
    "KALMAN", "EKF", "IEKF", "UKF", "METHODS", "FilterOptions", "Discretization", "discretize",
    "stationary_covariance", "FilterResult", "SmootherResult",
]
