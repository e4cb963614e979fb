"""Model specification: equations as text (or Python functions) to JAX functions."""

from .._collector import imports_frozen

# JAX, SymPy, pandas and these modules load here, once, with the collector paused (see greyid._collector).
with imports_frozen():
    from .model import ModelSpec
    from .parameters import Parameter
    from .structure import LTI, LTV, NONLINEAR, Structure

__all__ = ["ModelSpec", "Parameter", "Structure", "LTI", "LTV", "NONLINEAR"]
