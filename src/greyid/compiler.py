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
import numpy as np


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
        self.executables: dict = {}  # see executable()

    def __call__(self, *args, **kwargs):
        traced = any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves((args, kwargs)))
        return (self.nested if traced else self.top)(*args, **kwargs)

    def executable(self, *args):
        """The program compiled ahead of time for these arguments' shapes and types, kept.

        Callers that run one program from several threads at once compile it
        first: through ``__call__`` each thread's first call would wait for (or
        repeat) the compilation.
        """
        leaves, tree = jax.tree_util.tree_flatten(args)
        key = (tree, tuple((np.shape(a), a.dtype if hasattr(a, "dtype") else np.result_type(a)) for a in leaves))
        if key not in self.executables:
            self.executables[key] = self.top.lower(*args).compile(compiler_options())
        return self.executables[key]


def jit(fun, **kwargs) -> Jitted:
    """``jax.jit`` with greyid's compiler options."""
    return Jitted(fun, **kwargs)
