"""Model specification: equations as text (or Python functions) to JAX functions."""

from .model import ModelSpec
from .parameters import Parameter
from .structure import LTI, LTV, NONLINEAR, Structure

__all__ = ["ModelSpec", "Parameter", "Structure", "LTI", "LTV", "NONLINEAR"]
