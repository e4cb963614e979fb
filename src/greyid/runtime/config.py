"""JAX as greyid needs it: 64-bit floats and a persistent compilation cache.

Imported (through ``greyid.runtime``) by every module of greyid that computes with JAX,
before JAX itself.  It switches JAX to 64-bit floats (the filters need them; this applies to
every JAX user in the process) and, unless a cache folder is configured already,
turns on JAX's persistent compilation cache in ``$GREYID_CACHE_DIR`` (default
``~/.cache/greyid/jax``; ``off`` keeps it off, and with it the traced programs of
[`greyid.runtime.store`][greyid.runtime.store]).  JAX's own threshold applies to the process: programs
that compile in under a second are not kept; greyid's kept programs are kept however fast
([`kept_however_fast()`][greyid.runtime.jit.kept_however_fast], a setting of the compiling thread only).
"""

from __future__ import annotations

import os

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


def enable_compilation_cache() -> None:
    """JAX's persistent compilation cache in greyid's cache folder, unless the user configured one
    (or the folder cannot be used: then a [`CacheWarning`][greyid.errors.CacheWarning] says why)."""
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
        from ..errors import CacheWarning, warn

        warn(f"greyid's cache folder '{path}' {problem}: compiled programs are not kept between processes "
             "(set GREYID_CACHE_DIR to a writable folder, or to off)", CacheWarning)
        return
    if jax.config.jax_compilation_cache_dir is None:  # respect a cache the user configured
        jax.config.update("jax_compilation_cache_dir", path)


enable_compilation_cache()
