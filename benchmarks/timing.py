"""The timers of the benchmark scripts: a first call (with compilation) and the best of repeated ones."""

from __future__ import annotations

import time


def timed(label, fun, repeat=1):
    """Run ``fun`` once, then ``repeat`` more times; print the first call and the best again; return its result."""
    start = time.perf_counter()
    out = fun()
    first = time.perf_counter() - start
    again = []
    for _ in range(repeat):
        start = time.perf_counter()
        fun()
        again.append(time.perf_counter() - start)
    extra = f", compiled {min(again):.3f} s (best of {repeat})" if repeat else ""
    print(f"  {label}: first call {first:.2f} s{extra}")
    return out


def durations(fun, count: int) -> tuple[list, object]:
    """The seconds of ``count`` calls of ``fun`` one after the other, and the last call's result."""
    seconds, out = [], None
    for _ in range(count):
        start = time.perf_counter()
        out = fun()
        seconds.append(time.perf_counter() - start)
    return seconds, out


def fastest(fun, calls: int = 300) -> float:
    """The fastest of ``calls`` calls of ``fun`` (after one more, not counted), in seconds."""
    fun()
    return min(durations(fun, calls)[0])
