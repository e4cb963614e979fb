"""Python's cyclic garbage collector paused while greyid imports its dependencies.

Importing JAX, SymPy and pandas creates about 240 000 objects that live as
long as the process; automatic full collections among them take a part of a
first fit, and every later one would walk them all again.  They are imported
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
