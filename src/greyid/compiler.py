"""How greyid compiles its functions.

Every jitted function of the package goes through :func:`jit`, so compiler
settings live in one place.  On CPUs, XLA's newer fusion emitters take about
twice as long to compile a filter's scan as the classic ones and run it no
faster (measured on the test-cell and Armadillo models, ``benchmarks/fit.py``),
and compile time is most of a first fit.  XNNPACK's fusions are off: they turn
the products and sums over a state's two or three elements into library calls,
which made a scoring step of a 10⁵-row series 3 times and its Hessian 5 times
slower (``benchmarks/length.py``).

A function given a ``key`` — a description of everything its program depends
on besides its arguments' shapes — also keeps its traced program on disk
(:mod:`greyid.programs`), so that a later process skips tracing it.  Such a
program can be asked for *quick first* (a small fit's value–gradient–Hessian
program): where no process has compiled it yet, it is compiled at once with
LLVM's optimisations off (:data:`QUICK`) and the search runs on that; once the
search is done the optimised executable compiles in a background thread, goes
into JAX's persistent cache for later processes and replaces the quick one for
later calls in this one.

Python's garbage collector is paused while a program is traced and compiled
(:mod:`greyid._collector`).  XLA's compilation frees the interpreter, so
modules needed later (a fit's results) are imported meanwhile on the other
core (:func:`import_while_compiling`).
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import os
import sys
import threading
from typing import Callable

from . import _jax  # noqa: F401  (64-bit JAX before any JAX work)
import jax

from . import programs
from ._collector import collect_young_garbage, collector_paused


@functools.cache
def compiler_options() -> dict:
    if jax.default_backend() == "cpu":
        return {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""}
    return {}


#: XLA options of a program compiled for its first use only (see :meth:`Jitted.executable`):
#: the Armadillo fit's Hessian program compiles in 0.9 s instead of 1.4 s and runs
#: in twice the time (0.10 against 0.05 s for the fit), ``benchmarks/fit.py``.
QUICK = {"xla_backend_optimization_level": 0}


def quick_first_allowed() -> bool:
    """Whether programs may be compiled quick first (``GREYID_QUICK_FIRST=off`` says no).

    The command line says no: its process ends after the command and would wait
    for the optimised compilation anyway, so the quick one would only add to it.
    """
    return os.environ.get("GREYID_QUICK_FIRST", "on").lower() not in programs.OFF


_lock = threading.Lock()
_to_optimize: list[Callable] = []  # compilations of optimised executables not started yet
_optimizing: list[threading.Thread] = []  # and those running in the background


def optimize_quick_programs() -> None:
    """Start compiling the optimised executables of the programs compiled quick first.

    Called when the searches that use the quick executables are done, so that the
    compilation does not take the second core from their evaluations.  Each runs in
    a thread that is not a daemon: a process that ends first waits for it, so that
    the executable is kept for the next one.
    """
    while _to_optimize:
        thread = threading.Thread(target=_to_optimize.pop(), name="greyid-optimize")
        _optimizing.append(thread)
        thread.start()


def settle() -> None:
    """Wait until the optimised executables of programs compiled quick first are in use."""
    optimize_quick_programs()
    while _optimizing:
        _optimizing.pop().join()


_unkept = {"open": 0, "opened": 0}  # blocks of _not_kept_by_jax: open now, opened ever


@contextlib.contextmanager
def _not_kept_by_jax():
    """JAX's persistent cache not written for the block's compilations.

    JAX's setting is process-wide: a compilation in another thread that ends
    meanwhile is not kept either (:meth:`Jitted._optimize` checks for that).
    """
    setting = "jax_persistent_cache_min_compile_time_secs"
    with _lock:
        if _unkept["open"] == 0:
            _unkept["previous"] = getattr(jax.config, setting)
            jax.config.update(setting, float("inf"))
        _unkept["open"] += 1
        _unkept["opened"] += 1
    try:
        yield
    finally:
        with _lock:
            _unkept["open"] -= 1
            if _unkept["open"] == 0:
                jax.config.update(setting, _unkept["previous"])


_pending_imports: set[str] = set()
importer: threading.Thread | None = None  # the latest thread beside a compilation


def import_while_compiling(*modules: str) -> None:
    """Import ``modules`` in a thread during the next XLA compilation (unless imported by then).

    Compiling the Hessian program of a small model takes 1.3–1.5 s of C++ with
    the interpreter free; the modules a fit needs afterwards (its results:
    pandas tables, SciPy's distributions, 0.15–0.25 s) load meanwhile.
    """
    _pending_imports.update(modules)


def _beside_compilation(modules):
    for module in modules:
        try:
            importlib.import_module(module)
        except Exception:  # noqa: BLE001  raised again where the module is used
            pass
    collect_young_garbage()


def compile_lowered(lowered, *options):
    """``lowered.compile(*options)``, with pending imports and the collection of what
    tracing left behind running beside it (see :func:`collect_young_garbage`)."""
    global importer
    pending = sorted(m for m in _pending_imports if m not in sys.modules)
    _pending_imports.clear()
    importer = threading.Thread(target=_beside_compilation, args=(pending,), daemon=True)
    importer.start()
    return lowered.compile(*options)


class Jitted:
    """A jitted function that takes greyid's compiler options when called at top level.

    JAX accepts compiler options only on an outermost ``jit``; called inside
    another traced function (its arguments are tracers), the plain jitted
    function is used and the outer one's options apply.  With a ``key``, a
    top-level call runs the program of :meth:`executable`, loaded from disk
    where an earlier process kept it.
    """

    def __init__(self, fun, key=None, **kwargs):
        functools.update_wrapper(self, fun)
        self.top = jax.jit(fun, compiler_options=compiler_options(), **kwargs)
        self.nested = jax.jit(fun, **kwargs)
        self.key = key if not kwargs else None  # static arguments would need their values in the key
        self.executables: dict = {}  # see executable()

    def __call__(self, *args, **kwargs):
        leaves = jax.tree_util.tree_leaves((args, kwargs))
        if any(isinstance(a, jax.core.Tracer) for a in leaves):
            return self.nested(*args, **kwargs)
        if self.key is not None and not kwargs and programs.enabled():
            return self.executable(*args)(*args)
        with collector_paused():  # a first call traces and compiles
            return self.top(*args, **kwargs)

    def executable(self, *args, quick_first: bool = False):
        """The program compiled ahead of time for these arguments' shapes and types, kept.

        Callers that run one program from several threads at once compile it
        first: through ``__call__`` each thread's first call would wait for (or
        repeat) the compilation.  With ``quick_first``, a kept program that no
        process has compiled with optimisations yet is compiled quickly for this
        call (see the module's docstring); callers that fix the executable for a
        whole search keep its answers independent of when the optimised one is ready.
        """
        leaves, tree = jax.tree_util.tree_flatten(args)
        signature = (tree, tuple(jax.typeof(a) for a in leaves))
        if signature not in self.executables:
            with collector_paused():
                kept = programs.kept_lowering(self, args) if self.key is not None and programs.enabled() else None
                if kept is None:
                    self.executables[signature] = compile_lowered(self.top.lower(*args), compiler_options())
                elif quick_first and quick_first_allowed() and not kept.optimized_mark.exists():
                    # Not kept in JAX's cache (0.09 s): a later process wants the optimised one.
                    with _not_kept_by_jax():
                        self.executables[signature] = kept.runner(compile_lowered(kept.lowered, QUICK))
                    _to_optimize.append(functools.partial(self._optimize, signature, kept))
                else:
                    self.executables[signature] = kept.runner(compile_lowered(kept.lowered))
        return self.executables[signature]

    def _optimize(self, signature, kept) -> None:
        """Compile the optimised executable (kept in JAX's cache) and use it from then on."""
        try:
            with _lock:
                opened = _unkept["opened"] if _unkept["open"] == 0 else None
            self.executables[signature] = kept.runner(kept.lowered.compile())
            with _lock:
                kept_by_jax = opened == _unkept["opened"]  # no quick compilation meanwhile
            if kept_by_jax:
                programs.write(kept.optimized_mark, b"")
        except Exception:  # noqa: BLE001  the quick executable stays in use
            pass


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
