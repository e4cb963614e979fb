"""How greyid compiles its functions.

Every jitted function of the package goes through [`jit()`][greyid.compiler.jit], so compiler
settings live in one place.  On CPUs, XLA's newer fusion emitters take about
twice as long to compile a filter's scan as the classic ones and run it no
faster (measured on the test-cell and Armadillo models, ``benchmarks/fit.py``),
and compile time is most of a first fit.  XNNPACK's fusions are off: they turn
the products and sums over a state's two or three elements into library calls,
which made a scoring step of a 10⁵-row series 3 times and its Hessian 5 times
slower (``benchmarks/length.py``).  The memory-optimised instruction scheduler
orders a program's kernels for fewer live buffers rather than for running
independent ones side by side, which a filter's small kernels gain nothing from:
with it the Armadillo filter's value and gradient and its Hessian run faster
(``benchmarks/likelihood.py``).

A function given a ``key`` — a description of everything its program depends
on besides its arguments' shapes — also keeps its traced program on disk
([`greyid.programs`][greyid.programs]), so that a later process skips tracing it.  Every
program is compiled with the same options, whichever process or cache state
compiles it first, so that no answer depends on the cache.

XLA's compilation frees the interpreter: a program can compile in a thread while the next one is
traced ([`compile_in_background()`][greyid.compiler.compile_in_background]).
"""

from __future__ import annotations

import functools
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

from . import _jax  # noqa: F401  (64-bit JAX before any JAX work)
import jax

from . import programs


#: The XLA options greyid asks for on CPUs (see the module doc).  Some are experimental: each is
#: passed only where this jaxlib's XLA accepts it ([`compiler_options()`][greyid.compiler.compiler_options]).
CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": "",
               "xla_cpu_scheduler_type": "CPU_SCHEDULER_TYPE_MEMORY_OPTIMIZED"}


@functools.cache
def compiler_options() -> dict:
    """The options of [`CPU_OPTIONS`][greyid.compiler.CPU_OPTIONS] this JAX and XLA accept (none elsewhere, or on a JAX
    whose ``jit`` takes no compiler options): an upgrade that drops or renames one compiles
    with XLA's default for it instead of failing."""
    if jax.default_backend() != "cpu":
        return {}
    return {name: value for name, value in CPU_OPTIONS.items() if accepted({name: value})}


def accepted(options: dict) -> bool:
    """Whether a trivial program compiles with the XLA ``options``."""
    try:
        jax.jit(lambda x: x + 1.0, compiler_options=options).lower(1.0).compile()
    except Exception:  # noqa: BLE001  an unknown option, or a jit without compiler_options
        return False
    return True


def jax_jit(fun, **kwargs):
    """``jax.jit`` with greyid's compiler options, where there are any."""
    options = compiler_options()
    return jax.jit(fun, compiler_options=options, **kwargs) if options else jax.jit(fun, **kwargs)


def compile_lowered(lowered, *options):
    """``lowered.compile(*options)``: XLA's compilation of a traced and lowered program."""
    return lowered.compile(*options)


def compile_in_background(compile_program: Callable) -> Future:
    """The executable of ``compile_program`` (from [`Jitted.lowered()`][greyid.compiler.Jitted.lowered]) as a
    future: compiled in a thread while the caller goes on (XLA frees the interpreter), or at once where it
    was compiled already (no thread)."""
    if compile_program.compiled:
        done: Future = Future()
        done.set_result(compile_program())
        return done

    pool = ThreadPoolExecutor(1)
    future = pool.submit(compile_program)
    pool.shutdown(wait=False)  # the thread ends with its one task
    return future


class Jitted:
    """A jitted function that takes greyid's compiler options when called at top level.

    JAX accepts compiler options only on an outermost ``jit``; called inside
    another traced function (its arguments are tracers), the plain jitted
    function is used and the outer one's options apply.  With a ``key``, a
    top-level call runs the program of `executable()`, loaded from disk
    where an earlier process kept it.
    """

    def __init__(self, fun, key=None, **kwargs):
        functools.update_wrapper(self, fun)
        self.fun, self.kwargs, self._top = fun, kwargs, None
        self.nested = jax.jit(fun, **kwargs)
        self.key = key if not kwargs else None  # static arguments would need their values in the key
        self.executables: dict = {}  # see executable()

    @property
    def top(self):
        """The jitted function with greyid's compiler options (made at first use: finding which
        options this XLA accepts compiles a trivial program)."""
        if self._top is None:
            self._top = jax_jit(self.fun, **self.kwargs)
        return self._top

    def __call__(self, *args, **kwargs):
        leaves = jax.tree_util.tree_leaves((args, kwargs))
        if any(isinstance(a, jax.core.Tracer) for a in leaves):
            return self.nested(*args, **kwargs)
        if self.key is not None and not kwargs and programs.enabled():
            return self.executable(*args)(*args)
        return self.top(*args, **kwargs)

    def executable(self, *args):
        """The program compiled ahead of time for these arguments' shapes and types, kept.

        Callers that run one program from several threads at once compile it
        first: through ``__call__`` each thread's first call would wait for (or
        repeat) the compilation.
        """
        return self.lowered(*args)()

    def lowered(self, *args) -> Callable:
        """Trace (or load the kept trace) and lower the program now; the function returned
        compiles it (XLA, which frees the interpreter: in another thread, if wished) and keeps
        and returns the executable, as `executable()` does (its ``compiled`` attribute: True
        where the program was compiled already).

        So two programs compile side by side after being traced one after the other, and a
        function traced inside the first (a nested ``jit``) is not traced again for the second.
        """
        leaves, tree = jax.tree_util.tree_flatten(args)
        signature = (tree, tuple(jax.typeof(a) for a in leaves))
        if signature in self.executables:
            def ready():
                return self.executables[signature]

            ready.compiled = True  # nothing left to do: no thread needed
            return ready
        kept = programs.kept_lowering(self, args, jax_jit) if self.key is not None and programs.enabled() else None
        if kept is None:
            lowered = self.top.lower(*args)

            def build():
                return compile_lowered(lowered)
        else:
            def build():
                return kept.runner(compile_lowered(kept.lowered))

        def compiled():
            if signature not in self.executables:
                self.executables[signature] = build()
            return self.executables[signature]

        compiled.compiled = False
        return compiled


def jit(fun, key=None, **kwargs) -> Jitted:
    """``jax.jit`` with greyid's compiler options; ``key`` keeps the traced program on disk."""
    return Jitted(fun, key=key, **kwargs)


def structure_program(structure, key: tuple, make: Callable, **kwargs) -> Jitted:
    """The jitted ``make()`` for one model structure and settings ``key``, built once per structure.

    ``key`` must name every setting ``make`` closes over besides the structure:
    with the structure's fingerprint (models written as equations) it is also
    the program's key on disk.
    """
    if key not in structure.cache:
        fun = make()
        fun = fun.__wrapped__ if isinstance(fun, Jitted) else fun
        structure.cache[key] = jit(fun, key=kept_key(structure, key), **kwargs)
    return structure.cache[key]


def kept_key(structure, key: tuple):
    """The key on disk of a program of ``structure`` with settings ``key``: None for models of
    Python functions (no fingerprint), whose programs are never kept."""
    return None if structure.fingerprint is None else ("structure", structure.fingerprint, key)
