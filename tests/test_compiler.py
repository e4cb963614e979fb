"""How greyid compiles (greyid.compiler, greyid._collector): the garbage collector paused and
restored around imports, XLA's options, and the scan's initial carries tied to θ changing no number."""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import threading

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import greyid
from greyid import compiler
from greyid._collector import collector_paused, imports_frozen
from greyid.filters import gaussian


def test_the_collector_is_paused_in_the_block_and_restored_after_the_last_one():
    assert gc.isenabled()
    inside = threading.Event()
    release = threading.Event()

    def other_block():
        with collector_paused():
            inside.set()
            release.wait(10)

    with collector_paused():
        assert not gc.isenabled()
        worker = threading.Thread(target=other_block)
        worker.start()
        inside.wait(10)
        with collector_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()
    assert not gc.isenabled(), "re-enabled while another thread's block is still open"
    release.set()
    worker.join()
    assert gc.isenabled()
    # A collector the user switched off stays off.
    gc.disable()
    try:
        with collector_paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()


def test_imports_run_with_the_collector_paused_and_what_they_made_is_frozen():
    seen = []

    def record(phase, info):
        seen.append(phase)

    from greyid import _process

    gc.unfreeze()
    gc.callbacks.append(record)
    _process._owned["on"] = True  # as in greyid's own command-line process
    try:
        with imports_frozen():
            assert not gc.isenabled()
            made = [[i] for i in range(100_000)]  # enough to trigger automatic collections
            assert seen == []
        assert gc.isenabled()
        assert gc.get_freeze_count() >= len(made)
        assert not any(o is made for o in gc.get_objects()), "frozen objects are left out of collections"
        # Inside another paused block, or with the collector switched off by the user: nothing frozen.
        gc.unfreeze()
        with collector_paused():
            with imports_frozen():
                pass
        assert gc.get_freeze_count() == 0
        gc.disable()
        try:
            with imports_frozen():
                pass
            assert not gc.isenabled() and gc.get_freeze_count() == 0
        finally:
            gc.enable()
        # A user's process (not greyid's command line): paused, never frozen.
        _process._owned["on"] = False
        with imports_frozen():
            assert not gc.isenabled()
        assert gc.isenabled() and gc.get_freeze_count() == 0
    finally:
        _process._owned["on"] = False
        gc.callbacks.remove(record)
        gc.unfreeze()


def test_only_greyids_own_process_is_frozen_and_keeps_every_program(tmp_path):
    """A user's script: greyid freezes none of its objects and leaves JAX's minimum compile time of the
    persistent cache alone; greyid's command line (its own process) freezes its imports and keeps
    every program."""
    user = ("import gc, jax, greyid; before = jax.config.jax_persistent_cache_min_compile_time_secs; "
            "import greyid.model, sys; assert 'jax' in sys.modules and 'sympy' in sys.modules; "
            "assert gc.isenabled() and gc.get_freeze_count() == 0, gc.get_freeze_count(); "
            "assert jax.config.jax_persistent_cache_min_compile_time_secs == before")
    subprocess.run([sys.executable, "-c", user], check=True)
    own = ("import gc; from greyid import _process; _process.take_over(); import greyid.model, jax; "
           "assert gc.isenabled() and gc.get_freeze_count() > 100_000, gc.get_freeze_count(); "
           "assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0")
    subprocess.run([sys.executable, "-c", own], check=True, env=dict(os.environ, GREYID_CACHE_DIR=str(tmp_path)))
    off = ("import gc; from greyid import _process; _process.take_over(); gc.disable(); import greyid.model; "
           "assert not gc.isenabled() and gc.get_freeze_count() == 0")
    subprocess.run([sys.executable, "-c", off], check=True)


def test_the_estimation_package_loads_its_results_module_only_when_used():
    code = ("import sys, greyid.estimate as e; assert 'greyid.estimate.results' not in sys.modules; "
            "from greyid.estimate import Estimates; "
            "assert Estimates is sys.modules['greyid.estimate.results'].Estimates")
    subprocess.run([sys.executable, "-c", code], check=True)


def ou_model():
    m = greyid.Model("ou_fixed_p0")
    m.add_system("dx = theta*(mu - x)*dt + exp(ls)*dw1")
    m.add_observation("y = x", variance="exp(le)")
    m.set_initial_state(mean={"x": "x0"}, covariance=[[1.0]])  # P0 independent of θ
    for name, value, low, high in [("theta", 1.0, 0.01, 20), ("mu", 0.5, -10, 10), ("ls", -1.0, -10, 3),
                                   ("le", -3.0, -10, 3), ("x0", 0.0, -10, 10)]:
        m.set_parameter(name, value, lower=low, upper=high)
    return m


def test_tying_the_initial_carries_to_theta_changes_no_number(monkeypatch):
    truth = {"theta": 0.8, "mu": 1.0, "ls": -1.0, "le": -3.0, "x0": 0.5}
    times = pd.DataFrame({"t": np.arange(150) * 0.5})
    data = times.assign(y=ou_model().simulate(truth, times, method="exact", seed=5).outputs[0, :, 0])
    tied = ou_model().fit(data)
    monkeypatch.setattr(gaussian, "carried_from_start", lambda theta, *initial: tuple(initial))
    untied = ou_model().fit(data)
    assert tied.loglik == pytest.approx(untied.loglik, rel=1e-13)
    np.testing.assert_allclose(tied.params["estimate"], untied.params["estimate"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(tied.params["std_error"], untied.params["std_error"], rtol=1e-10)
    assert tied.iterations == untied.iterations


def test_an_xla_option_this_jaxlib_does_not_know_is_left_out(monkeypatch):
    """A JAX upgrade that drops or renames an (experimental) XLA option must not fail every compilation:
    the option is left out and XLA's default applies."""


    monkeypatch.setattr(compiler, "CPU_OPTIONS", dict(compiler.CPU_OPTIONS, xla_no_such_option_in_any_xla=True))
    compiler.compiler_options.cache_clear()
    try:
        options = compiler.compiler_options()
        assert "xla_no_such_option_in_any_xla" not in options
        assert "xla_cpu_use_fusion_emitters" in options  # known to this jaxlib: kept
        assert float(compiler.jit(lambda x: jnp.sin(x) * 2.0)(0.5)) == pytest.approx(2 * np.sin(0.5))
    finally:
        compiler.compiler_options.cache_clear()


def test_a_jit_without_compiler_options_compiles_with_none(monkeypatch):
    """JAX versions whose jit takes no compiler_options: greyid compiles with JAX's defaults."""
    import jax


    real = jax.jit

    def old_jit(fun, **kwargs):
        if "compiler_options" in kwargs:
            raise TypeError("jit() got an unexpected keyword argument 'compiler_options'")
        return real(fun, **kwargs)

    monkeypatch.setattr(jax, "jit", old_jit)
    compiler.compiler_options.cache_clear()
    try:
        assert compiler.compiler_options() == {}
        assert float(compiler.jit(lambda x: jnp.cos(x))(0.25)) == pytest.approx(np.cos(0.25))
    finally:
        monkeypatch.setattr(jax, "jit", real)
        compiler.compiler_options.cache_clear()
