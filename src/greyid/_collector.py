"""Python's cyclic garbage collector paused while greyid imports its dependencies and
while it traces and compiles a program.

Tracing allocates hundreds of thousands of objects that die young, and every
automatic full collection among them walks the whole heap of JAX, SymPy and
pandas: a noticeable part of an Armadillo first fit in a fresh process went to it
(``benchmarks/fit.py``), a small part with the collector paused.  What tracing leaves
behind is collected while XLA compiles, which frees the interpreter
([`collect_young_garbage()`][greyid._collector.collect_young_garbage]), or else after the
block, as usual.

Importing JAX, SymPy and pandas creates about 240 000 objects that live as
long as the process; the automatic full collections among them took a part of
the same fit, and every later one would walk them all again.  They are imported
with the collector paused, and in greyid's own command-line processes then
frozen ([`imports_frozen()`][greyid._collector.imports_frozen]); a user's process keeps its collector's state.
"""

from __future__ import annotations

import contextlib
import gc
import threading

_paused = {"depth": 0, "was_enabled": False}
_lock = threading.Lock()


@contextlib.contextmanager
def collector_paused():
    """The collector off for the block; nested blocks and threads: off until the last one exits."""
    with _lock:
        if _paused["depth"] == 0:
            _paused["was_enabled"] = gc.isenabled()
            gc.disable()
        _paused["depth"] += 1
    try:
        yield
    finally:
        with _lock:
            _paused["depth"] -= 1
            if _paused["depth"] == 0 and _paused["was_enabled"]:
                gc.enable()


@contextlib.contextmanager
def imports_frozen():
    """The collector paused while the block imports modules; in greyid's own processes
    ([`greyid._process.take_over()`][greyid._process.take_over]) every object tracked so far is then frozen.

    ``gc.freeze`` moves the objects to a permanent generation that later
    collections skip: modules, classes and functions, which live on anyway.
    It would also take a user's objects (a reference cycle among them that
    became garbage later would stay in memory), so a user's process is not
    frozen.  Nothing is frozen where the collector was switched off, or inside
    another paused block.
    """
    from ._process import owned

    with collector_paused():
        yield
        if _paused["depth"] == 1 and _paused["was_enabled"] and owned():
            gc.freeze()


def collect_young_garbage() -> None:
    """Collect the youngest generation now, if the pause is to end with the collector on.

    Run beside a compilation: the collection that would otherwise follow the
    paused block, on the interpreter's critical path, finds little left to do.
    """
    if _paused["depth"] > 0 and _paused["was_enabled"]:
        gc.collect(0)
