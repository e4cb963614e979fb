"""Continuous–discrete filters (chapter 4, appendix A): Kalman, EKF, IEKF, UKF."""

from .protocol import EKF, EKF2, IEKF, KALMAN, METHODS, UKF, FilterOptions
from .discretize import Discretization, discretize, stationary_covariance
from .result import FilterResult, SmootherResult

__all__ = [
    "KALMAN", "EKF", "EKF2", "IEKF", "UKF", "METHODS", "FilterOptions", "Discretization", "discretize",
    "stationary_covariance", "FilterResult", "SmootherResult",
]
