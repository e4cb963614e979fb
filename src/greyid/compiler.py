"""How greyid compiles its functions.

Every jitted function of the package goes through :func:`jit`, so compiler
settings live in one place.  On CPUs, XLA's newer fusion emitters take about
twice as long to compile a filter's scan as the classic ones and run it no
faster (measured on the test-cell and Armadillo models, ``benchmarks/fit.py``),
and compile time is most of a first fit.
"""

from __future__ import annotations

import functools

from . import _jax  # noqa: F401  (64-bit JAX before any JAX work)
import jax


@functools.cache
def compiler_options() -> dict:
    if jax.default_backend() == "cpu":
        return {"xla_cpu_use_fusion_emitters": False}
    return {}


class Jitted:
    """A jitted function that takes greyid's compiler options when called at top level.

    JAX accepts compiler options only on an outermost ``jit``; called inside
    another traced function (its arguments are tracers), the plain jitted
    function is used and the outer one's options apply.
    """

    def __init__(self, fun, **kwargs):
        functools.update_wrapper(self, fun)
        self.top = jax.jit(fun, compiler_options=compiler_options(), **kwargs)
        self.nested = jax.jit(fun, **kwargs)
        self.compiled_for: set = set()  # signatures callers have compiled (see Derivatives)

    def __call__(self, *args, **kwargs):
        traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves((args, kwargs)))
        return (self.nested if traced else self.top)(*args, **kwargs)


def jit(fun, **kwargs) -> Jitted:
    """``jax.jit`` with greyid's compiler options."""
    return Jitted(fun, **kwargs)
