"""How greyid compiles (greyid.runtime): one jit for nested and top-level calls, XLA's options, and the
scan's initial carries tied to θ changing no number."""

from __future__ import annotations

import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.runtime import jit as compiler
from greyid.filters import gaussian


def test_the_estimation_package_loads_its_results_module_only_when_used():
    code = ("import sys, greyid.estimate as e; assert 'greyid.estimate.results' not in sys.modules; "
            "from greyid.estimate import Estimates; "
            "assert Estimates is sys.modules['greyid.estimate.results'].Estimates")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_fit_many_after_a_fit_imports_no_statistics_library():
    """A script that fits a model and then a fleet: ``greyid.fit_many`` loads the fleet modules without
    scipy.stats (half a second to import, and a fleet fit uses none of it); ``run_study``'s critical
    values still work."""
    code = ("import sys, greyid, greyid.api; assert 'scipy.stats' not in sys.modules, 'before'; greyid.fit_many; "
            "assert 'scipy.stats' not in sys.modules, 'fit_many'; "
            "from greyid.fleet.study import StudyResult; import pandas as pd; "
            "r = StudyResult.__new__(StudyResult); r.estimates = pd.DataFrame({'a': [1.0, 2.0, 3.0]}); "
            "v = r.critical_values(0.1); assert 1.0 < v['t'] < 3.0, v")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_population_fit_imports_no_statistics_library():
    """``greyid.fit_population`` and its result load without scipy.stats (half a second to import, and a
    population fit uses none of it): the 95 % quantile is SciPy's normal quantile itself."""
    code = ("import sys; from greyid.population import fit_population; from greyid.population import result; "
            "assert 'scipy.stats' not in sys.modules; from scipy import stats; "
            "assert result.Z95 == float(stats.norm.ppf(0.975)), result.Z95")
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


def test_a_compile_without_options_compiles_with_none(monkeypatch):
    """A JAX whose compile() takes no XLA options: greyid compiles with JAX's defaults."""
    import jax

    real = jax.stages.Lowered.compile

    def old_compile(self, compiler_options=None, **kwargs):
        if compiler_options:
            raise TypeError("compile() got an unexpected argument 'compiler_options'")
        return real(self, **kwargs)

    monkeypatch.setattr(jax.stages.Lowered, "compile", old_compile)
    compiler.compiler_options.cache_clear()
    try:
        assert compiler.compiler_options() == {}
        assert float(compiler.jit(lambda x: jnp.cos(x))(0.25)) == pytest.approx(np.cos(0.25))
    finally:
        monkeypatch.setattr(jax.stages.Lowered, "compile", real)
        compiler.compiler_options.cache_clear()


def test_one_jit_serves_nested_and_top_level_calls_with_the_options(compilations):
    """A program called inside another traced function runs as that program's part (XLA takes options
    only for the outermost one).  At top level a kept program (one with a key) runs an executable
    compiled with greyid's options, one per signature (tree, shapes, kinds, weak types, static values;
    a NumPy array or scalar and a JAX array are one kind);
    one without a key runs JAX's own dispatch of the function jitted with those options."""
    import jax

    scaled = compiler.jit(lambda x, a: jnp.sin(x) * a)
    assert float(scaled(0.5, 2.0)) == pytest.approx(2 * np.sin(0.5))
    assert float(jax.grad(scaled)(0.5, 2.0)) == pytest.approx(2 * np.cos(0.5))  # nested: traced
    outer = compiler.jit(lambda x: scaled(x, 3.0) + 1.0)
    assert float(outer(0.25)) == pytest.approx(3 * np.sin(0.25) + 1.0)
    assert scaled._top is not None and not scaled.executables and not compilations

    kept = compiler.Program(lambda x, a: jnp.sin(x) * a, key=("test", "kept"))
    assert float(kept(0.5, 2.0)) == pytest.approx(2 * np.sin(0.5))
    assert float(jax.grad(kept)(0.5, 2.0)) == pytest.approx(2 * np.cos(0.5))
    np.testing.assert_allclose(np.asarray(kept(np.ones(3), 2.0)), 2 * np.sin(np.ones(3)))
    kept(0.7, 1.0)  # the same signature as the first call: no new compilation
    kept(np.float64(0.7), 1.0)  # a NumPy scalar is strongly typed: another program
    assert len(kept.executables) == 3 and len(compilations) == 3
    # A JAX array of a NumPy array's shape and dtype runs the program compiled for the NumPy one, and
    # the other way round (a fleet's members bring NumPy arrays to a program compiled for device arrays).
    np.testing.assert_allclose(np.asarray(kept(jnp.asarray(np.full(3, 0.3)), 2.0)), 2 * np.sin(np.full(3, 0.3)))
    np.testing.assert_allclose(np.asarray(kept(np.ones((2, 2)), jnp.asarray(np.float64(2.0)))),
                               2 * np.sin(np.ones((2, 2))))
    np.testing.assert_allclose(np.asarray(kept(jnp.ones((2, 2)), np.asarray(3.0))), 3 * np.sin(np.ones((2, 2))))
    kept(np.float64(0.5), 2.0)  # a NumPy scalar: as a 0-dimensional array (the program of np.float64(0.7))
    assert len(kept.executables) == 4 and len(compilations) == 4
    kept(np.ones(3, dtype=np.float32), 2.0)  # another dtype: another program
    assert len(kept.executables) == 5 and len(compilations) == 5
    powers = compiler.Program(lambda x, n: x ** n, key=("test", "powers"), static_argnums=(1,))
    assert float(powers(2.0, 3)) == 8.0 and float(powers(2.0, 2)) == 4.0 and float(powers(3.0, 2)) == 9.0
    unkept_powers = compiler.jit(lambda x, n: x ** n, static_argnums=(1,))
    assert float(unkept_powers(2.0, 3)) == 8.0 and float(unkept_powers(3.0, 2)) == 9.0


def test_only_greyids_own_process_is_frozen_and_keeps_every_program(tmp_path):
    """A user's script: greyid freezes none of its objects and leaves JAX's minimum compile time of the
    persistent cache alone; greyid's command line (its own process) loads its layers with the collector
    paused, freezes them and keeps every program; a collector the user switched off stays off."""
    user = ("import gc, jax, greyid; before = jax.config.jax_persistent_cache_min_compile_time_secs; "
            "import greyid.model, greyid.api, sys; assert 'jax' in sys.modules and 'sympy' in sys.modules; "
            "assert gc.isenabled() and gc.get_freeze_count() == 0, gc.get_freeze_count(); "
            "assert jax.config.jax_persistent_cache_min_compile_time_secs == before")
    # JAX's own default, not the one conftest.py sets for the suite's processes:
    plain = {key: value for key, value in __import__("os").environ.items()
             if key != "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"}
    subprocess.run([sys.executable, "-c", user], check=True, env=plain)
    own = ("import gc; from greyid import cli; cli.OWN_PROCESS['on'] = True; cli._load_layers(); import jax; "
           "assert gc.isenabled() and gc.get_freeze_count() > 100_000, gc.get_freeze_count(); "
           "assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0")
    env = dict(plain, GREYID_CACHE_DIR=str(tmp_path))
    subprocess.run([sys.executable, "-c", own], check=True, env=env)
    off = ("import gc; from greyid import cli; cli.OWN_PROCESS['on'] = True; gc.disable(); cli._load_layers(); "
           "assert not gc.isenabled() and gc.get_freeze_count() == 0")
    subprocess.run([sys.executable, "-c", off], check=True, env=env)
    called = ("import gc; from greyid import cli; cli._load_layers(); "  # main([...]) from a user's script
              "assert gc.get_freeze_count() == 0 and 'greyid.api' not in __import__('sys').modules")
    subprocess.run([sys.executable, "-c", called], check=True, env=env)


def test_a_user_process_keeps_greyids_fast_compilations_and_not_its_own(tmp_path):
    """In a user's script (JAX's minimum compile time of the persistent cache at its default), a program of
    greyid's that compiles in well under a second is kept in the cache folder for later processes; the user's
    own program is not, and JAX's setting is left as it was."""
    code = ("import os, jax, jax.numpy as jnp; from greyid.runtime.jit import jit; "
            "jit(lambda x: jnp.sin(x) * 3.0, key=('test', 'kept however fast'))(1.5); "
            "jax.jit(lambda x: jnp.cos(x) * 5.0)(2.5); "
            "assert jax.config.jax_persistent_cache_min_compile_time_secs == 1.0; "
            "print(len([n for n in os.listdir(os.environ['GREYID_CACHE_DIR']) if n.endswith('-cache')]))")
    env = {key: value for key, value in __import__("os").environ.items()
           if key != "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"}
    env["GREYID_CACHE_DIR"] = str(tmp_path)
    kept = subprocess.run([sys.executable, "-c", code], check=True, env=env, capture_output=True, text=True)
    assert kept.stdout.split()[-1] == "1"


def test_a_jax_without_the_thread_local_setting_compiles_as_before(monkeypatch):
    """kept_however_fast() reaches into JAX's internal configuration: where that setting has no thread-local
    form (moved or changed in a later JAX), greyid's programs compile and run under JAX's default."""
    import contextlib

    from jax._src import config as jax_config

    class Moved:  # the setting as a plain value, no context
        value = 1.0

    monkeypatch.setattr(jax_config, "persistent_cache_min_compile_time_secs", Moved())
    assert isinstance(compiler.kept_however_fast(), contextlib.nullcontext)
    program = compiler.jit(lambda x: jnp.tan(x) * 2.0, key=("test", "without the thread-local setting"))
    assert float(program(0.3)) == pytest.approx(2 * np.tan(0.3))


def test_the_tests_compilation_cache_is_pruned_oldest_first(tmp_path):
    """The folder the tests keep programs in between runs (XLA's at its top, traced ones in ``programs/``) is
    pruned to its limit at a run's start, the oldest files first wherever they are, and left alone under it."""
    import os

    from conftest import prune_oldest

    (tmp_path / "programs").mkdir()
    for age, name in enumerate(["newest", "programs/newer", "older", "programs/oldest"]):
        path = tmp_path / name
        path.write_bytes(b"x" * 100)
        os.utime(path, (1_000_000 - age, 1_000_000 - age))

    def left():
        return sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())

    prune_oldest(str(tmp_path), 400)
    assert len(left()) == 4
    prune_oldest(str(tmp_path), 250)
    assert left() == ["newest", "programs/newer"]


def test_a_test_marked_alone_runs_while_no_other_test_does(tmp_path):
    """conftest's taking_turns (run around every test): a block marked alone waits for the block that runs
    to end, and a block that comes while it waits or runs is told to wait (its memory released) and starts after it."""
    import threading
    import time

    from conftest import taking_turns

    events, lock = [], threading.Lock()

    def note(what):
        with lock:
            events.append(what)

    def block(name, alone, hold, started):
        with taking_turns(str(tmp_path), alone, waiting=lambda: note(f"{name} waits")):
            note(f"{name} in")
            started.set()
            time.sleep(hold)
            note(f"{name} out")

    def start(name, alone, hold, until_in=False):
        started = threading.Event()
        thread = threading.Thread(target=block, args=(name, alone, hold, started))
        thread.start()
        if until_in:
            started.wait()
        return thread

    threads = [start("first", False, 0.6, until_in=True), start("alone", True, 0.3)]
    time.sleep(0.2)  # the alone block holds the gate, waiting for the first to end
    threads.append(start("later", False, 0.0))
    for thread in threads:
        thread.join(10)
    assert events == ["first in", "later waits", "first out", "alone in", "alone out", "later in", "later out"]
    events.clear()  # a block that comes while the alone block runs (the gate free again) is told to wait too
    threads = [start("alone", True, 0.4, until_in=True), start("after", False, 0.0)]
    for thread in threads:
        thread.join(10)
    assert events == ["alone in", "after waits", "alone out", "after in", "after out"]
    with taking_turns(str(tmp_path), True):  # alone and nobody else: no wait
        pass


def test_a_test_that_replaces_part_of_greyid_runs_with_the_store_off(monkeypatch, tmp_path):
    """conftest's monkeypatch: changing the environment or the folder keeps greyid's kept traced programs on;
    replacing an attribute or an item (other than the environment's) switches them off for the test, as its
    change is in no program's key."""
    import os

    from greyid.runtime import store

    monkeypatch.setenv("GREYID_PROGRAMS", "on")
    monkeypatch.setenv("GREYID_SOME_SETTING", "1")
    monkeypatch.delenv("GREYID_SOME_SETTING")
    monkeypatch.chdir(tmp_path)
    assert store.switched_on()
    monkeypatch.setitem({}, "key", 1)
    assert not store.switched_on()
    monkeypatch.setenv("GREYID_PROGRAMS", "on")
    monkeypatch.setattr(store, "FORMAT", store.FORMAT)
    assert not store.switched_on() and os.environ["GREYID_PROGRAMS"] == "off"
