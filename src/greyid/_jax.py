"""JAX as greyid needs it, set up once, before greyid's first JAX computation.

Every module of greyid that uses JAX imports this one first.  It switches JAX
to 64-bit floats (the filters need them; this applies to every JAX user in the
process) and turns on JAX's persistent compilation cache in
``$GREYID_CACHE_DIR`` (default ``~/.cache/greyid/jax``; ``off`` keeps it off,
and with it the traced programs greyid keeps in its ``programs`` folder)
unless a cache directory is configured already; greyid's own command-line
processes also keep every program that compiles in under JAX's threshold (1 s).  ``import greyid`` alone
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


def cache_folder_problem(path: str) -> str | None:
    """Why ``path`` cannot be greyid's cache folder (a file, a broken or looping link, not writable),
    or None where it can (it may not exist yet: it is made when first needed)."""
    if os.path.islink(path) and not os.path.exists(path):
        return "is a symbolic link that leads nowhere (a loop or a missing target)"
    if os.path.exists(path) and not os.path.isdir(path):
        return "is a file, not a folder"
    if os.path.isdir(path) and not os.access(path, os.W_OK | os.X_OK):
        return "is not writable"
    return None


def _enable_compilation_cache() -> None:
    path = cache_dir()
    if path is None:
        return
    problem = cache_folder_problem(path)
    if problem is None:
        try:
            os.makedirs(path, exist_ok=True)
        except OSError as error:  # a read-only home, a file on the way
            problem = f"cannot be made ({error.strerror or error})"
    if problem is not None:
        from .errors import CacheWarning, warn

        warn(f"greyid's cache folder '{path}' {problem}: compiled programs are not kept between processes "
             "(set GREYID_CACHE_DIR to a writable folder, or to off)", CacheWarning)
        return
    if jax.config.jax_compilation_cache_dir is None:  # respect a cache the user configured
        jax.config.update("jax_compilation_cache_dir", path)
        if owned():
            # In greyid's own processes every program, however quick to compile: the report's
            # forty small ones would compile again in each process (greyid demo).
            # A user's process keeps JAX's threshold, so its own quick programs are not kept.
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


_enable_compilation_cache()
