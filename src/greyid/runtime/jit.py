"""One ``jit`` for every program of greyid, compiled with greyid's XLA options.

[`jit()`][greyid.runtime.jit.jit] wraps ``jax.jit``.  Called inside another traced function
(its arguments are tracers) the jitted function is used as it is: XLA takes compiler
options only for the outermost program.  Called at top level, the program is
compiled ahead of time for the arguments' shapes and types with the options of
[`CPU_OPTIONS`][greyid.runtime.jit.CPU_OPTIONS]: by a second ``jax.jit`` of the function with
those options (JAX's dispatch finds the executable for the arguments), or, for a program with a
``key``, ahead of time and kept per signature, its traced program coming from (or going to)
[`greyid.runtime.store`][greyid.runtime.store].  Every
program compiles with the same options whichever process or cache state compiles it
first, so that no answer depends on the cache.

The options, on CPUs: XLA's newer fusion emitters take about twice as long to
compile a filter's scan as the classic ones and run it no faster
(``benchmarks/fit.py``), and compile time is most of a first fit.  XNNPACK's fusions
are off: they turn the products and sums over a state's two or three elements into
library calls, which made a scoring step of a 10⁵-row series 3 times and its Hessian
5 times slower (``benchmarks/length.py``).  The memory-optimised instruction
scheduler orders a program's kernels for fewer live buffers rather than for running
independent ones side by side, which a filter's small kernels gain nothing from
(``benchmarks/likelihood.py``).  docs/performance.md has the figures.
"""

from __future__ import annotations

import contextlib
import functools
import weakref
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

import jax
import numpy as np

from . import store

#: The XLA options greyid asks for on CPUs (see the module doc).  Some are experimental: each is
#: passed only where this jaxlib's XLA accepts it ([`compiler_options()`][greyid.runtime.jit.compiler_options]).
CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": "",
               "xla_cpu_scheduler_type": "CPU_SCHEDULER_TYPE_MEMORY_OPTIMIZED"}


@functools.cache
def compiler_options() -> dict:
    """The options of [`CPU_OPTIONS`][greyid.runtime.jit.CPU_OPTIONS] this JAX and XLA accept (none on other
    backends): an upgrade that drops or renames one compiles with XLA's default for it instead of failing."""
    if jax.default_backend() != "cpu":
        return {}
    return {name: value for name, value in CPU_OPTIONS.items() if accepted({name: value})}


def accepted(options: dict) -> bool:
    """Whether a trivial program compiles with the XLA ``options``."""
    try:
        jax.jit(lambda x: x + 1.0).lower(1.0).compile(options)
    except Exception:  # noqa: BLE001  an unknown option, or a compile() without options
        return False
    return True


#: The compiled programs of kept keys in this process, by key and signature, held weakly: a model built
#: anew (a notebook cell run again, a new model object for each fit) finds the programs of an equal model
#: that is still alive compiled, instead of loading or compiling them again.  A key names everything its
#: traced program depends on (it is the program's name on disk), so the executable is the one a compilation
#: would give.  ``GREYID_PROGRAMS=off`` switches it off with the store (a process that replaces greyid's
#: functions or constants at run time, as some of its tests do, must not be given programs built before).
_compiled_by_key: weakref.WeakValueDictionary = weakref.WeakValueDictionary()

#: Every [`Program`][greyid.runtime.jit.Program] of this process, held weakly, for
#: [`release_compiled()`][greyid.runtime.jit.release_compiled].
_programs: weakref.WeakSet = weakref.WeakSet()


def compile_lowered(lowered):
    """XLA's compilation of a traced and lowered program, with greyid's options, kept in JAX's persistent
    cache however fast it compiled ([`kept_however_fast()`][greyid.runtime.jit.kept_however_fast])."""
    options = compiler_options()
    with kept_however_fast():
        return lowered.compile(options) if options else lowered.compile()


def kept_however_fast():
    """A context in which JAX's persistent compilation cache keeps what this thread compiles, however fast.

    JAX keeps by default only programs that took a second or more to compile, so a later process compiled
    greyid's smaller programs (a population's closed forms) again.  The setting is
    thread-local: the user's own programs keep JAX's.  JAX has no public form of it; where its internal one
    is missing or changed, nothing changes (those programs compile in every process, as with JAX's default).
    """
    try:
        from jax._src import config as jax_config

        return jax_config.persistent_cache_min_compile_time_secs(0.0)
    except Exception:  # noqa: BLE001  an internal API that moved: JAX's default applies
        return contextlib.nullcontext()


#: The kind of a NumPy or JAX array (or NumPy scalar) leaf in a signature.
ARRAY = "array"
#: Whether a leaf's type is a NumPy or JAX array's (or a NumPy scalar's), by type: looked up per call.
_array_types: dict = {}


def _is_array_type(kind: type) -> bool:
    """Whether ``kind`` is a NumPy or JAX array's type (or a NumPy scalar's), noted in ``_array_types``."""
    array = _array_types[kind] = issubclass(kind, (np.ndarray, np.generic, jax.Array))
    return array


class Program:
    """A jitted function whose top-level calls run an executable compiled with greyid's options.

    Parameters
    ----------
    fun : callable
        The function of arrays (and pytrees of arrays) to compile.
    key : hashable, optional
        Everything the traced program depends on besides its arguments' shapes and types
        (see [`structure_program()`][greyid.runtime.jit.structure_program]); with it the traced
        program is kept on disk ([`greyid.runtime.store`][greyid.runtime.store]).
    static_argnums : tuple of int
        Arguments whose values, not shapes, the program depends on (as ``jax.jit``).
    """

    def __init__(self, fun: Callable, key=None, static_argnums: tuple[int, ...] = ()):
        functools.update_wrapper(self, fun)
        self.jitted = jax.jit(fun, static_argnums=static_argnums)
        self.static_argnums = tuple(static_argnums)
        self.key = None if static_argnums else key  # static values would have to be in the key
        self.executables: dict = {}  # signature -> compiled program (see executable())
        self._shared_key = None if self.key is None else repr(self.key)  # as on disk (store.path_for)
        self._top = None  # see top
        _programs.add(self)

    def __call__(self, *args):
        if any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(args)):
            return self.jitted(*args)
        if self.key is None:
            return self.top(*args)
        return self.executable(*args)(*self.dynamic(args))

    @property
    def top(self):
        """The function jitted with greyid's options, for top-level calls of a program not kept on disk:
        JAX's own dispatch (in C++) finds its executable for the arguments, a tenth of a likelihood
        evaluation faster than a signature of ours (``benchmarks/likelihood.py``)."""
        if self._top is None:
            options = compiler_options()
            kwargs = dict(static_argnums=self.static_argnums, **({"compiler_options": options} if options else {}))
            self._top = jax.jit(self.__wrapped__, **kwargs)
        return self._top

    def dynamic(self, args: tuple) -> tuple:
        """The arguments a compiled program takes (all but the static ones)."""
        if not self.static_argnums:
            return args
        return tuple(a for i, a in enumerate(args) if i not in self.static_argnums)

    def signature(self, args: tuple) -> tuple:
        """What a compiled program is specific to: the arguments' tree, each leaf's kind, shape, dtype
        and weak type (a Python float is weakly typed, a NumPy one is not), and the static values.

        A NumPy array (or scalar) and a JAX array of the same shape and dtype are one kind: a compiled
        program takes either (a fleet's members bring their series as NumPy arrays to the program a fit of
        one of them compiled for its arrays on the device).  Read from the leaves' attributes rather
        than ``jax.typeof``, which costs several times as much per leaf on every call; a compiled
        program checks its arguments again itself.
        """
        leaves, tree = jax.tree_util.tree_flatten(self.dynamic(args))
        known = _array_types
        kinds = tuple((ARRAY, a.shape, a.dtype, getattr(a, "weak_type", False))
                      if known.get(type(a)) or (type(a) not in known and _is_array_type(type(a))) else
                      (type(a), getattr(a, "shape", None), getattr(a, "dtype", None), getattr(a, "weak_type", None))
                      for a in leaves)
        return tree, kinds, tuple(args[i] for i in self.static_argnums)

    def lower(self, args: tuple):
        """The traced and lowered program for ``args``: from the store where it is kept there."""
        lowered = store.lowered(self.jitted, self.key, args) if self.key is not None else None
        return self.jitted.lower(*args) if lowered is None else lowered

    def executable(self, *args):
        """The program compiled for these arguments' shapes and types (and static values), kept.

        It takes the arguments other than the static ones.  Callers that run one program from
        several threads at once fetch it first: through ``__call__`` each thread's first call
        would compile it again.
        """
        signature = self.signature(args)
        found = self._compiled(signature)
        if found is None:
            found = self.executables[signature] = self._keep(signature, compile_lowered(self.lower(args)))
        return found

    def _compiled(self, signature):
        """The executable for ``signature`` compiled already: this program's own, else that of an equal
        program of this process that is still alive (then kept as its own); None if there is none."""
        found = self.executables.get(signature)
        if found is None and self._shared_key is not None and store.switched_on():
            found = _compiled_by_key.get((self._shared_key, signature))
            if found is not None:
                self.executables[signature] = found
        return found

    def _keep(self, signature, executable):
        if self._shared_key is not None and store.switched_on():
            _compiled_by_key[(self._shared_key, signature)] = executable
        return executable

    def compile_in_background(self, *args) -> Future:
        """`executable()` as a future: traced and lowered now, compiled by XLA in a thread (which frees
        the interpreter) while the caller goes on; done at once where it was compiled already. The
        caller runs the executable the future returns.

        A fit compiles its exact Hessian program so while its first scoring or quasi-Newton steps
        run, which shortens a quasi-Newton first fit by more than the 10 % a mechanism must buy
        (``benchmarks/runtime.py``, docs/performance.md).
        """
        signature = self.signature(args)
        found = self._compiled(signature)
        if found is not None:
            done: Future = Future()
            done.set_result(found)
            return done
        lowered = self.lower(args)

        def compile_and_keep():
            found = self.executables[signature] = self._keep(signature, compile_lowered(lowered))
            return found

        pool = ThreadPoolExecutor(1)
        future = pool.submit(compile_and_keep)
        pool.shutdown(wait=False)  # the thread ends with its one task
        return future


def jit(fun: Callable, key=None, static_argnums: tuple[int, ...] = ()) -> Program:
    """``jax.jit`` with greyid's compiler options; ``key`` keeps the traced program on disk (see
    [`Program`][greyid.runtime.jit.Program])."""
    return Program(fun, key=key, static_argnums=static_argnums)


def structure_program(structure, key: tuple, make: Callable) -> Program:
    """The jitted ``make()`` for one model structure and settings ``key``, built once per structure.

    ``key`` must name every setting ``make`` closes over besides the structure:
    with the structure's fingerprint (models written as equations) it is also
    the program's key on disk.
    """
    if key not in structure.cache:
        fun = make()
        fun = fun.__wrapped__ if isinstance(fun, Program) else fun
        structure.cache[key] = jit(fun, key=kept_key(structure, key))
    return structure.cache[key]


def kept_key(structure, key: tuple):
    """The key on disk of a program of ``structure`` with settings ``key``: None for models of
    Python functions (no fingerprint), whose programs are never kept."""
    return None if structure.fingerprint is None else ("structure", structure.fingerprint, key)


def release_compiled(model=None) -> None:
    """Drop compiled programs this process holds: JAX's (``jax.clear_caches()``) and those greyid's programs
    keep for the models still alive, whose memory ``jax.clear_caches()`` alone does not free; or only those
    of ``model``.

    A long session (a notebook that has fitted many models, a model selection, a test suite) gets the
    memory back; a later call of a model's program loads it again from the cache folder (or compiles it
    where none is kept), with the same results.

    Parameters
    ----------
    model : greyid.Model, optional
        Release only the programs of this model's structure (and not JAX's caches); all when None.

    Examples
    --------
    >>> import greyid
    >>> from greyid.runtime.jit import release_compiled
    >>> model = greyid.library.load_model("Ti")
    >>> release_compiled(model)  # this model's programs only
    >>> release_compiled()  # every program of the process
    """
    if model is None:
        programs = list(_programs)
    else:
        programs = list(_programs_in(getattr(model, "structure", model).cache))
    for program in programs:
        program.executables.clear()
        program._top = None
    if model is None:
        jax.clear_caches()


def _programs_in(held):
    """The programs in ``held``: a structure's cache of programs, alone or in tuples, lists and dicts."""
    if isinstance(held, Program):
        yield held
    elif isinstance(held, dict):
        for value in held.values():
            yield from _programs_in(value)
    elif isinstance(held, (tuple, list)):
        for value in held:
            yield from _programs_in(value)
