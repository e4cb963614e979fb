"""Progress output for long work: optimiser iterations and loops over fits.

Quiet by default in the Python API (``progress=False``); the command line turns
it on.  ``progress=True`` writes to standard error through rich, so a bar
redraws in a terminal and plain lines go to a log; a callable receives one
dict per event instead, for notebooks or GUIs that show progress their own way.
"""

from __future__ import annotations

import threading
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")

#: Seconds without a first step after which a printed fit says what it waits for (the compilation of its
#: programs, on a first fit of a model).
QUIET_START = 2.0


def _console():
    from rich.console import Console

    return Console(stderr=True, highlight=False, soft_wrap=True)


#: What the cache folder does for a program's compilation, said in every waiting line.
KEPT = "greyid's cache folder keeps them for later runs"


class Waiting:
    """Says ``message`` once on standard error if the block it guards still runs after
    [`QUIET_START`][greyid.progress.QUIET_START] seconds: a first run of work that compiles programs
    (a report, residual tests) is otherwise seconds of silence.

    Parameters
    ----------
    message : str
        What the block waits for.
    enabled : bool
        False: say nothing (``--quiet``).

    Examples
    --------
    >>> with Waiting("  writing the report"):
    ...     pass
    """

    def __init__(self, message: str, enabled: bool = True):
        self.message = message
        self._timer = None
        if enabled:
            self._timer = threading.Timer(QUIET_START, lambda: _console().print(self.message))
            self._timer.daemon = True

    def __enter__(self) -> "Waiting":
        return self.start()

    def start(self) -> "Waiting":
        """Start waiting (what entering the block does)."""
        if self._timer is not None:
            self._timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        """Say nothing from now on (a line being said is finished first, so none comes after the block)."""
        if self._timer is not None:
            self._timer.cancel()
            self.join()

    def join(self) -> None:
        """Wait until the line is said or the waiting stopped."""
        if self._timer is not None and self._timer.is_alive():
            self._timer.join()


class FitProgress:
    """Reports a fit: each optimiser iteration (single start) or each finished start."""

    def __init__(self, progress, starts: int, label: str = "log-likelihood"):
        self.callback: Callable[[dict], None] | None = progress if callable(progress) else None
        self.enabled = bool(progress) and self.callback is None
        self.starts = starts
        self.label = label
        self._bar = None
        self._task = None
        self._start = 0
        self._waiting = None

    def __enter__(self) -> "FitProgress":
        if self.enabled:
            self.console = _console()
            # A first fit compiles its programs before its first step: seconds of silence otherwise.
            self._waiting = Waiting(f"  preparing the first step (more than {QUIET_START:g} s): a first fit of a "
                                    f"model compiles its programs; {KEPT}").start()
            if self.starts > 1:
                from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

                self._bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), console=self.console, transient=False)
                self._bar.start()
                self._task = self._bar.add_task("multi-start fit", total=self.starts)
        return self

    def __exit__(self, *exc) -> None:
        self._stop_waiting()
        if self._bar is not None:
            self._bar.stop()

    def _stop_waiting(self) -> None:
        if self._waiting is not None:
            self._waiting.stop()
            self._waiting = None

    def begin_start(self, index: int) -> None:
        self._start = index

    def iteration(self, iteration: int, stage: str, value: float, gradient: float, start: int | None = None) -> None:
        """One accepted step; ``value`` is the criterion to maximise (e.g. the log-likelihood).

        ``start`` names the start when several run together (batched starts).
        """
        self._stop_waiting()
        info = dict(start=self._start if start is None else start, iteration=iteration, stage=stage,
                    value=value, max_gradient=gradient)
        if self.callback is not None:
            self.callback(info)
        elif self.enabled and self.starts == 1:
            self.console.print(f"  {stage:6s} iter {iteration:4d}   {self.label} {value: .6f}   "
                               f"max|gradient| {gradient:.2e}")

    def end_start(self, value: float, iterations: int, converged: bool, message: str,
                  start: int | None = None) -> None:
        self._stop_waiting()
        if start is not None:
            self._start = start
        if self.callback is not None:
            self.callback(dict(start=self._start, finished=True, value=value, iterations=iterations,
                               converged=converged, message=message))
        elif self.enabled:
            where = f"start {self._start + 1}/{self.starts}: " if self.starts > 1 else ""
            self.console.print(f"  {where}{iterations} iterations, {self.label} {value:.6f}, {message}")
            if self._bar is not None:
                self._bar.advance(self._task)


class CountProgress:
    """A bar over a known number of pieces of work (the data sets of a fleet), advanced as each ends.

    ``progress`` as for [`track()`][greyid.progress.track]: true for a bar on standard error, a callable
    for ``(done, total)``, false for nothing.
    """

    def __init__(self, total: int, description: str, progress=False):
        self.total, self.description, self.progress, self.done = total, description, progress, 0
        self._bar = None

    def __enter__(self) -> "CountProgress":
        if self.progress and not callable(self.progress):
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), console=_console())
            self._bar.start()
            self._task = self._bar.add_task(self.description, total=self.total)
        return self

    def advance(self, count: int = 1) -> None:
        self.done += count
        if callable(self.progress):
            self.progress(self.done, self.total)
        elif self._bar is not None:
            self._bar.advance(self._task, count)

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.stop()


def track(items: Iterable[T], total: int, description: str, progress=False) -> Iterator[T]:
    """Iterate with a progress bar when ``progress`` is true; a callable gets ``(done, total)``."""
    if callable(progress):
        for i, item in enumerate(items):
            yield item
            progress(i + 1, total)
        return
    if not progress:
        yield from items
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=_console()) as bar:
        task = bar.add_task(description, total=total)
        for item in items:
            yield item
            bar.advance(task)
