"""Progress output and warnings of fits and studies."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.datasets import load_building_data
from greyid.datasets.building import building_model
from greyid.progress import track


@pytest.fixture(scope="module")
def short():
    return building_model(), load_building_data().iloc[:300]


def test_callable_progress_sees_every_iteration(short):
    model, data = short
    events = []
    fit = model.fit(data, progress=events.append)
    steps = [e for e in events if "iteration" in e]
    assert [e["iteration"] for e in steps] == list(range(1, len(steps) + 1))
    assert events[-1]["finished"] and events[-1]["value"] == pytest.approx(fit.loglik, rel=1e-12)
    values = [e["value"] for e in steps]
    assert all(b >= a - 1e-9 for a, b in zip(values, values[1:]))  # accepted steps never go down
    assert fit.iterations == len(steps)


def test_quiet_by_default_and_printed_when_asked(short, capsys):
    model, data = short
    model.fit(data)
    assert capsys.readouterr().err == ""
    model.fit(data, progress=True)
    err = capsys.readouterr().err
    assert "iter    1   log-likelihood" in err and "converged" in err
    model.fit(data, progress=True, starts=2, seed=1)
    err = capsys.readouterr().err
    assert "start 1/2:" in err and "start 2/2:" in err


def test_a_fit_slow_to_its_first_step_says_what_it_waits_for(short, capsys, monkeypatch):
    """Printed progress: past QUIET_START seconds without a first step, one line says that a first fit
    compiles its programs, before the first iteration's line; a fit that steps sooner prints none."""
    from greyid import progress

    model, data = short
    monkeypatch.setattr(progress, "QUIET_START", 0.0)
    real = progress.FitProgress.iteration

    def late(self, *args, **kwargs):  # the first step after the waiting line, however quick the fit
        if self._waiting is not None:
            self._waiting.join()
        return real(self, *args, **kwargs)

    monkeypatch.setattr(progress.FitProgress, "iteration", late)
    model.fit(data, progress=True)
    err = capsys.readouterr().err
    assert err.count("a first fit of a model compiles its programs") == 1
    assert err.index("compiles its programs") < err.index("iter    1")
    monkeypatch.setattr(progress.FitProgress, "iteration", real)
    monkeypatch.setattr(progress, "QUIET_START", 600.0)
    model.fit(data, progress=True)
    err = capsys.readouterr().err
    assert "compiles its programs" not in err and "iter    1" in err


def test_warnings_are_issued_and_stored():
    m = greyid.Model("bounded")
    m.add_system("dx = -a*x*dt + s*dw1")
    m.add_observation("y = x", variance="v")
    m.set_initial_state(mean={"x": 0.0}, covariance=[1.0])
    m.set_parameter("a", init=0.5, lower=0.1, upper=0.6)  # the truth, 2, lies beyond the upper bound
    m.set_parameter("s", init=1.0, lower=1e-3, upper=10)
    m.set_parameter("v", init=0.1, lower=1e-4, upper=10)
    t = np.arange(200) * 0.1
    sim = m.simulate({"a": 2.0, "s": 1.0, "v": 0.01}, t, seed=3)
    with pytest.warns(greyid.FitWarning, match="'a' is at a bound"):
        fit = m.fit(pd.DataFrame({"t": t, "y": sim.outputs[0, :, 0]}))
    assert any("'a' is at a bound" in w for w in fit.warnings)
    # a quantity free of the parameter at its bound keeps its standard error
    derived = fit.derived({"inverse noise": "1/s", "with a": "a*s"})
    assert np.isfinite(derived.loc["inverse noise", "std_error"])
    assert np.isnan(derived.loc["with a", "std_error"])


def test_track_reports_to_a_callable():
    seen = []
    assert list(track(range(4), 4, "x", progress=lambda d, n: seen.append((d, n)))) == [0, 1, 2, 3]
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert list(track(range(2), 2, "x")) == [0, 1]


def test_a_waiting_line_is_said_once_only_while_its_block_runs_past_quiet_start(capsys, monkeypatch):
    """Waiting (the command line's report and residual tests): the line after QUIET_START seconds, once;
    none for a quicker block, none when not enabled, none after the block has ended."""
    import time

    from greyid import progress

    monkeypatch.setattr(progress, "QUIET_START", 0.05)
    with progress.Waiting("  compiling the report"):
        time.sleep(1.0)  # (time for the timer's thread on a loaded machine)
    assert capsys.readouterr().err.count("compiling the report") == 1
    with progress.Waiting("  compiling the report", enabled=False):
        time.sleep(0.2)
    monkeypatch.setattr(progress, "QUIET_START", 0.5)
    with progress.Waiting("  compiling the report"):
        pass
    time.sleep(0.7)
    assert "compiling" not in capsys.readouterr().err
