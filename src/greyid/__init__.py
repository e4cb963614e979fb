"""greyid: grey-box identification of physical systems with stochastic differential equations.

Importing greyid switches JAX to 64-bit floats, which the filters need, and
turns on JAX's persistent compilation cache (in ``$GREYID_CACHE_DIR``, by
default ``~/.cache/greyid/jax``) so that a model compiled once is not compiled
again in a later process.  Set ``GREYID_CACHE_DIR=off`` to keep it off.
"""

import os

import jax

jax.config.update("jax_enable_x64", True)


def _enable_compilation_cache() -> None:
    path = os.environ.get("GREYID_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "greyid", "jax"))
    if path.lower() in ("off", "0", "none", ""):
        return
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return  # a read-only home: run without the cache
    if jax.config.jax_compilation_cache_dir is None:  # respect a cache the user configured
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


_enable_compilation_cache()

from .errors import DataError, ModelError  # noqa: E402
from .model import Model  # noqa: E402
from .estimate import FitResult, FitWarning, load_fit  # noqa: E402

__version__ = "0.1.0"
__all__ = ["Model", "FitResult", "FitWarning", "load_fit", "ModelError", "DataError", "__version__"]
