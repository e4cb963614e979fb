"""greyid: grey-box identification of physical systems with stochastic differential equations.

``import greyid`` is light: JAX, SymPy and the rest load when a model is first
used (``greyid.Model``, ``greyid.load_fit``, ...).  Then greyid switches JAX to
64-bit floats, which the filters need, and turns on JAX's persistent
compilation cache (see [`greyid.runtime`][greyid.runtime]; ``GREYID_CACHE_DIR=off`` keeps it off).
"""

import sys

from .errors import DataError, FitWarning, ModelError, UndeterminedWarning

__version__ = "0.1.0"
__all__ = ["Model", "FitResult", "FitWarning", "load_fit", "fit_many", "FleetResult", "fit_population",
           "PopulationResult", "ModelError", "DataError", "UndeterminedWarning", "__version__"]

if "jax" in sys.modules:  # JAX is in use already: make it 64-bit now, as before any work
    from . import runtime  # noqa: F401

_LAZY = {"Model": "api", "FitResult": "api", "load_fit": "api",
         "fit_many": "fleet", "FleetResult": "fleet", "fit_population": "population",
         "PopulationResult": "population"}


#: Subpackages reachable as attributes after ``import greyid`` alone (``greyid.datasets.fetch``,
#: ``greyid.design.identifiability``), imported when first named.
_SUBPACKAGES = ("datasets", "library", "data", "model", "filters", "estimate", "simulate", "uncertainty",
                "validation", "design", "report", "fleet", "population")


def __getattr__(name):
    if name in _SUBPACKAGES:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'greyid' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY) + list(_SUBPACKAGES))
