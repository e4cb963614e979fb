"""Python's cyclic garbage collector paused while greyid traces and compiles a program.

Tracing allocates hundreds of thousands of objects that die young, and every
automatic full collection among them walks the whole heap of JAX, SymPy and
pandas: 0.2–0.25 s of an Armadillo first fit in a fresh process went to it
(``benchmarks/fit.py``), 0.03 s with the collector paused.  What tracing leaves
behind is collected while XLA compiles, which frees the interpreter
(:func:`collect_young_garbage`, 0.03 s of the same fit), or else after the
block, as usual.  (Pausing it during
the imports of JAX and SymPy gains nothing: what they allocate lives on, and the
first collection afterwards walks it all.)
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


def collect_young_garbage() -> None:
    """Collect the youngest generation now, if the pause is to end with the collector on.

    Run beside a compilation: the collection that would otherwise follow the
    paused block, on the interpreter's critical path, finds little left to do.
    """
    if _paused["depth"] > 0 and _paused["was_enabled"]:
        gc.collect(0)
