"""JAX as greyid needs it, set up once, before greyid's first JAX computation.

Every module of greyid that uses JAX imports this one first.  It switches JAX
to 64-bit floats (the filters need them; this applies to every JAX user in the
process) and turns on JAX's persistent compilation cache in
``$GREYID_CACHE_DIR`` (default ``~/.cache/greyid/jax``; ``off`` keeps it off,
and with it the traced programs greyid keeps in its ``programs`` folder)
unless a cache directory is configured already; greyid's own compilations are
kept however quick (:func:`greyid.compiler.kept_however_quick`), and greyid's own
command-line processes also keep every other program that compiles in under JAX's
threshold (1 s).  ``import greyid`` alone
imports neither JAX nor SymPy, so the command line's help and version answer at
once; the first use of a model does.
"""

import os

from ._collector import imports_frozen
from ._process import owned

with imports_frozen():  # see greyid._collector
    import jax

jax.config.update("jax_enable_x64", True)


def cache_dir() -> str | None:
    """greyid's cache folder (``$GREYID_CACHE_DIR``), or None where it is switched off."""
    path = os.environ.get("GREYID_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "greyid", "jax"))
    return None if path.lower() in ("off", "0", "none", "") else path


def _enable_compilation_cache() -> None:
    path = cache_dir()
    if path is None:
        return
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return  # a read-only home: run without the cache
    if jax.config.jax_compilation_cache_dir is None:  # respect a cache the user configured
        jax.config.update("jax_compilation_cache_dir", path)
        if owned():
            # In greyid's own processes every program, however quick to compile: the report's
            # forty small ones took 1.2 s to compile in each process (greyid demo, 11.9 → 10.7 s).
            # A user's process keeps JAX's threshold, so its own quick programs are not kept.
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


_enable_compilation_cache()
