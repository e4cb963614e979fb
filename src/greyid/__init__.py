"""greyid: grey-box identification of physical systems with stochastic differential equations.

Importing greyid switches JAX to 64-bit floats, which the filters need.
"""

import jax

jax.config.update("jax_enable_x64", True)

from .errors import DataError, ModelError  # noqa: E402
from .model import Model  # noqa: E402

__version__ = "0.1.0"
__all__ = ["Model", "ModelError", "DataError", "__version__"]
