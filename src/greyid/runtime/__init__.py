"""greyid's compile runtime, in three parts.

* [`config`][greyid.runtime.config]: 64-bit JAX and greyid's cache folder, set when the
  first module of greyid that computes with JAX is imported (each imports ``greyid.runtime``
  before JAX);
* [`jit`][greyid.runtime.jit]: one ``jit`` for every program of greyid, which compiles a
  top-level call with greyid's XLA options;
* [`store`][greyid.runtime.store]: traced programs kept on disk with ``jax.export``, so
  that a later process skips tracing them (``GREYID_PROGRAMS=off`` switches it off).

``import greyid`` alone imports none of them (nor JAX), so the command line's help and
version answer at once.
"""

from . import config  # noqa: F401  (64-bit JAX and the cache folder before any JAX work)
