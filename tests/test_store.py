"""Programs kept on disk (greyid.runtime.store): a later fit loads them and gets the same answer;
anything that changes the program changes its key; nothing else is ever loaded."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import jax

import greyid
from greyid.runtime import jit as compiler
from greyid.runtime import store as programs

# These tests switch the store on and off themselves, in a cache folder of their own (the cache fixture),
# and replace its parts to watch them: conftest's monkeypatch leaves GREYID_PROGRAMS to them.
pytestmark = pytest.mark.own_program_store

SPEC = "dx = theta*(mu - x)*dt + exp(ls)*dw1"


def ou_model(drift=SPEC):
    m = greyid.Model("ou")
    m.add_system(drift)
    m.add_observation("y = x", variance="exp(le)")
    m.set_initial_state(mean={"x": "x0"}, covariance=[[1.0]])
    m.set_parameter("theta", 1.0, lower=0.01, upper=20)
    m.set_parameter("mu", 0.5, lower=-10, upper=10)
    m.set_parameter("ls", -1.0, lower=-10, upper=3)
    m.set_parameter("le", -3.0, lower=-10, upper=3)
    m.set_parameter("x0", 0.0, lower=-10, upper=10)
    return m


@pytest.fixture(scope="module")
def ou_data():
    truth = {"theta": 0.8, "mu": 1.0, "ls": -1.0, "le": -3.0, "x0": 0.5}
    times = pd.DataFrame({"t": np.arange(200) * 0.5})
    sim = ou_model().simulate(truth, times, method="exact", seed=3)
    return times.assign(y=sim.outputs[0, :, 0])


def as_in_a_new_process(monkeypatch):
    """Forget the programs this process compiled for kept keys, as a new process would not have them: a new
    model of equal equations otherwise takes them from a live one, without reading the store."""
    import weakref

    monkeypatch.setattr(compiler, "_compiled_by_key", weakref.WeakValueDictionary())


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GREYID_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("GREYID_PROGRAMS", "on")
    as_in_a_new_process(monkeypatch)
    return tmp_path / "programs"


def kept_files(folder):
    return sorted(folder.glob("*.jaxexport")) if folder.exists() else []


def test_a_later_fit_loads_the_kept_program_and_gets_the_same_answer(cache, ou_data, monkeypatch):
    first = ou_model().fit(ou_data)
    files = kept_files(cache)
    assert files, "the fit's derivatives program was not kept"
    # A new model of the same equations (a new structure, as in a new process) loads, never exports.
    def refuse(*args, **kwargs):
        raise AssertionError("exported again although a kept program matches")

    monkeypatch.setattr(programs.jax.export, "export", refuse)
    as_in_a_new_process(monkeypatch)
    model = ou_model()
    loaded = model.fit(ou_data)
    assert kept_files(cache) == files
    program = model.structure.cache[next(k for k in model.structure.cache if k[0] == "objective")].derivatives
    assert program.executables
    assert loaded.loglik == pytest.approx(first.loglik, abs=1e-9)
    np.testing.assert_allclose(loaded.params["estimate"], first.params["estimate"], rtol=1e-9)
    np.testing.assert_allclose(loaded.params["std_error"], first.params["std_error"], rtol=1e-7)


@pytest.mark.slow
def test_another_equation_or_setting_is_another_program(cache, ou_data):
    ou_model().fit(ou_data)
    count = len(kept_files(cache))
    ou_model("dx = theta*(mu - x)*dt + exp(ls)*x*dw1").fit(ou_data)  # other diffusion: other fingerprint
    assert len(kept_files(cache)) > count
    count = len(kept_files(cache))
    ou_model().fit(ou_data, method="ekf")  # other filter
    assert len(kept_files(cache)) > count
    model = ou_model()
    key = ("objective", "x")
    assert programs.path_for(key, (np.zeros(4),)) != programs.path_for(key, (np.zeros(3),))
    assert programs.path_for(key, (np.zeros(3, dtype=np.int64),)) != programs.path_for(key, (np.zeros(3),))
    assert model.structure.fingerprint == ou_model().structure.fingerprint
    assert model.structure.fingerprint != ou_model(SPEC.replace("mu - x", "x - mu")).structure.fingerprint


def test_python_function_models_and_switched_off_cache_keep_nothing(cache, tmp_path, ou_data, monkeypatch):
    import jax.numpy as jnp

    m = greyid.Model.from_functions(
        states=["x"], outputs=["y"], parameters=["theta", "mu", "ls", "le"],
        drift=lambda x, u, t, p: jnp.array([p["theta"] * (p["mu"] - x[0])]),
        diffusion=lambda x, u, t, p: jnp.array([[jnp.exp(p["ls"])]]),
        observation=lambda x, u, t, p: jnp.array([x[0]]),
        observation_variance=lambda x, u, t, p: jnp.array([jnp.exp(p["le"])]), kind="lti")
    m.set_initial_state(mean={"x": 0.5}, covariance=[[1.0]])
    for name, value in {"theta": 1.0, "mu": 0.5, "ls": -1.0, "le": -3.0}.items():
        m.set_parameter(name, value, lower=-10 if name != "theta" else 0.01, upper=20)
    assert m.structure.fingerprint is None
    m.fit(ou_data)
    assert kept_files(tmp_path / "programs") == []
    monkeypatch.setenv("GREYID_PROGRAMS", "off")
    assert not programs.enabled()
    ou_model().fit(ou_data)
    assert kept_files(cache) == []
    monkeypatch.setenv("GREYID_PROGRAMS", "on")
    monkeypatch.setenv("GREYID_CACHE_DIR", "off")
    assert not programs.enabled()


def test_an_unreadable_kept_program_is_traced_again_and_repaired(cache, ou_data, monkeypatch):
    first = ou_model().fit(ou_data)
    for path in kept_files(cache):
        path.write_bytes(b"not a program")
    as_in_a_new_process(monkeypatch)
    again = ou_model().fit(ou_data)
    assert again.loglik == pytest.approx(first.loglik, abs=1e-9)
    for path in kept_files(cache):  # rewritten: readable again
        programs.unseal(path.read_bytes())


def test_kept_programs_are_not_pickles_and_a_changed_byte_is_caught(cache, ou_data, monkeypatch):
    """A kept file is JAX's serialized program followed by its SHA-256: nothing executable.  One byte
    changed in the program (a float constant, say) is caught by the hash: the file is removed and
    exported again, and the answer is the traced one."""
    import hashlib

    model = ou_model()
    first = model.fit(ou_data)
    files = kept_files(cache)
    assert files
    for path in files:
        data = path.read_bytes()
        assert hashlib.sha256(data[:-32]).digest() == data[-32:]
        assert not data.startswith(b"\x80")  # a pickle's first byte
        exported = jax.export.deserialize(bytearray(programs.unseal(data)))
        assert exported.in_tree.num_leaves >= 1  # the arguments' tree travels with the program
    values = first.values
    reference = ou_model().loglik(values, ou_data)
    for path in files:
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0x01
        path.write_bytes(bytes(data))
        with pytest.raises(ValueError, match="hash"):
            programs.unseal(bytes(data))
    exported = []
    real_export = programs.jax.export.export

    def counting(*args, **kwargs):
        exported.append(1)
        return real_export(*args, **kwargs)

    monkeypatch.setattr(programs.jax.export, "export", counting)
    as_in_a_new_process(monkeypatch)
    again = ou_model().fit(ou_data)
    assert exported, "the damaged program was exported again"
    assert again.loglik == pytest.approx(first.loglik, abs=1e-9)
    assert ou_model().loglik(values, ou_data) == pytest.approx(reference, abs=1e-12)
    for path in kept_files(cache):
        programs.unseal(path.read_bytes())


def test_the_cache_command_shows_and_clears_the_folder(cache, ou_data, tmp_path):
    from greyid.cli import main

    ou_model().fit(ou_data)
    usage = programs.usage()
    assert usage["programs"][0] >= 1 and usage["programs"][1] > 0
    assert main(["cache", "info"]) == 0
    assert programs.clear() >= usage["programs"][0]
    assert programs.usage()["programs"] == (0, 0) and kept_files(cache) == []


def test_greyids_named_tuples_travel_by_name_and_every_program_of_a_fit_is_kept(cache, ou_data, monkeypatch):
    """The filters' and the estimator's named tuples in a program's arguments and results serialize with
    JAX's own tree serialization (registered by module and name); none of a fit's keyed programs falls
    back to tracing."""
    from greyid.filters.updates import StepTerms

    programs.register_named_tuples()
    assert StepTerms in programs._registered
    fallbacks = []
    real = programs.lowered

    def watching(jitted, key, args):
        out = real(jitted, key, args)
        if out is None:
            fallbacks.append(key)
        return out

    monkeypatch.setattr(programs, "lowered", watching)
    ou_model().fit(ou_data)
    ou_model().fit(ou_data, method="ekf")
    assert fallbacks == []


@pytest.mark.slow
def test_a_new_equal_model_in_the_process_takes_the_live_ones_programs_and_another_does_not(
        cache, ou_data, compilations, monkeypatch):
    """A model built anew from the same equations (a notebook cell run again) finds the programs of an equal
    model that is alive compiled: it compiles nothing and gets the same answer to the last bit.  Another
    equation, another filter or other shapes compile their own; once no model holds a program, it is gone;
    ``GREYID_PROGRAMS=off`` shares nothing."""
    import gc

    monkeypatch.setenv("GREYID_CACHE_DIR", "off")  # sharing in the process needs no cache folder
    first_model = ou_model()
    first = first_model.fit(ou_data)
    compiled = len(compilations)
    assert compiled
    again = ou_model().fit(ou_data)
    assert len(compilations) == compiled
    assert again.loglik == first.loglik and again.iterations == first.iterations
    np.testing.assert_array_equal(again.params["estimate"], first.params["estimate"])
    np.testing.assert_array_equal(again.params["std_error"], first.params["std_error"])
    other = ou_model("dx = theta*(mu - x)*dt + exp(ls)*x*dw1").fit(ou_data)
    assert len(compilations) > compiled
    assert other.loglik != first.loglik
    compiled = len(compilations)
    ou_model().fit(ou_data, method="ekf")  # another filter: another key
    assert len(compilations) > compiled
    compiled = len(compilations)
    ou_model().fit(ou_data.iloc[:150])  # other shapes
    assert len(compilations) > compiled
    assert len(compiler._compiled_by_key) > 0
    monkeypatch.setenv("GREYID_PROGRAMS", "off")
    compiled = len(compilations)
    alone = ou_model().fit(ou_data)
    assert len(compilations) > compiled and alone.loglik == first.loglik
    del first_model, first, again, other
    gc.collect()
    assert len(compiler._compiled_by_key) == 0


def test_released_programs_of_a_live_model_are_freed_and_its_next_fit_is_the_same(cache, ou_data, compilations):
    """release_compiled() drops the executables a live model's programs keep (jax.clear_caches() alone
    leaves them): none is left alive in the process; the model's next fit compiles its programs again
    (from the kept ones) and gives the same answer to the last bit."""
    import gc

    from jax.stages import Compiled

    def alive():
        gc.collect()
        return sum(isinstance(thing, Compiled) for thing in gc.get_objects())

    model = ou_model()
    first = model.fit(ou_data)
    jax.clear_caches()
    assert alive() > 0 and any(program.executables for program in compiler._programs)
    compiler.release_compiled()
    assert alive() == 0
    assert not any(program.executables for program in compiler._programs) and len(compiler._compiled_by_key) == 0
    compiled = len(compilations)
    again = model.fit(ou_data)
    assert len(compilations) > compiled
    assert again.loglik == first.loglik and again.iterations == first.iterations
    np.testing.assert_array_equal(again.params["estimate"], first.params["estimate"])
    np.testing.assert_array_equal(again.params["std_error"], first.params["std_error"])


def test_a_fit_does_not_depend_on_the_cache_state(cache, ou_data, compilations, monkeypatch):
    """Every program compiles with the same options whichever process or cache state compiles it:
    a first fit (empty caches), a fit in the same process, and a new model's (a new process's) fit on
    the kept programs give the same estimates, and JAX's cache setting is never toggled."""
    setting = jax.config.jax_persistent_cache_min_compile_time_secs
    model = ou_model()
    first = model.fit(ou_data)
    again = model.fit(ou_data)
    as_in_a_new_process(monkeypatch)
    later = ou_model().fit(ou_data)
    assert compilations  # every compilation went through compile_lowered, with greyid's options
    assert jax.config.jax_persistent_cache_min_compile_time_secs == setting
    assert not hasattr(compiler, "QUICK") and not hasattr(compiler, "settle")
    for other in (again, later):
        assert other.loglik == pytest.approx(first.loglik, rel=1e-13)
        np.testing.assert_allclose(other.params["estimate"], first.params["estimate"], rtol=1e-12)
        np.testing.assert_allclose(other.params["std_error"], first.params["std_error"], rtol=1e-10)
        assert other.iterations == first.iterations


LAPACK_SCRIPT = """
import sys
import numpy as np, pandas as pd
sys.path.insert(0, sys.argv[1])
from test_store import ou_model
data = pd.read_csv(sys.argv[2])
m = ou_model()
m.set_initial_state(mean={"x": "x0"}, covariance="stationary")  # solved by LU: LAPACK on CPUs
values = {"theta": 0.9, "mu": 0.8, "ls": -1.1, "le": -2.9, "x0": 0.4}
print(repr(m.fit(data).loglik), repr(m.loglik(values, data)))
"""


def test_a_kept_program_that_calls_lapack_runs_in_a_fresh_process(tmp_path, ou_data):
    """A kept program that calls LAPACK (a stationary initial covariance, solved by LU), loaded by a
    process that traced nothing, computes what tracing computes."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    data = tmp_path / "data.csv"
    ou_data.to_csv(data, index=False)
    env = dict(os.environ, GREYID_CACHE_DIR=str(tmp_path / "cache"), GREYID_PROGRAMS="on")
    runs = [subprocess.run([sys.executable, "-c", LAPACK_SCRIPT, str(Path(__file__).parent), str(data)], env=env,
                           check=True, capture_output=True, text=True).stdout.split() for _ in range(2)]
    kept = kept_files(tmp_path / "cache" / "programs")
    assert any(b"custom_call" in path.read_bytes() for path in kept)
    m = ou_model()
    m.set_initial_state(mean={"x": "x0"}, covariance="stationary")
    traced = m.fit(ou_data).loglik
    values = {"theta": 0.9, "mu": 0.8, "ls": -1.1, "le": -2.9, "x0": 0.4}
    for fit_loglik, loglik in runs:
        assert float(fit_loglik) == pytest.approx(traced, abs=1e-9)
        assert float(loglik) == pytest.approx(m.loglik(values, ou_data), abs=1e-12)


def test_a_likelihood_keeps_its_programs_under_its_data_and_frees_them_on_release(cache, ou_data, monkeypatch):
    """model.likelihood's programs hold the data as constants, so they are kept under the data's digest: a later
    process with the same data loads them (bitwise the same value, gradient and Hessian); other data of the same
    shape are another program, with their own value; release_compiled() frees the executables it holds."""
    import gc

    from jax.stages import Compiled

    x = np.array([0.9, 0.8, -1.1, -2.9, 0.4])
    first = ou_model().likelihood(ou_data)
    expected = (*first.value_and_grad(x), first.hessian(x), first.value(np.stack([x, x + 0.01])))
    files = kept_files(cache)
    assert len(files) == 3  # value and gradient, Hessian, the batched value

    def refuse(*args, **kwargs):
        raise AssertionError("exported again although a kept program matches")

    with monkeypatch.context() as loading:
        loading.setattr(programs.jax.export, "export", refuse)
        as_in_a_new_process(loading)
        again = ou_model().likelihood(ou_data)
        loaded = (*again.value_and_grad(x), again.hessian(x), again.value(np.stack([x, x + 0.01])))
    for a, b in zip(loaded, expected):
        np.testing.assert_array_equal(a, b)
    assert kept_files(cache) == files

    other = ou_data.assign(y=ou_data["y"] + 0.5)  # the same shapes, other values
    value = ou_model().likelihood(other).value(x)
    assert len(kept_files(cache)) == len(files) + 1
    assert value == pytest.approx(-ou_model().loglik(dict(zip(first.names, x)), other), rel=1e-12)
    assert abs(value - expected[0]) > 1.0

    compiler.release_compiled()  # with the likelihoods alive
    gc.collect()
    assert not any(isinstance(thing, Compiled) for thing in gc.get_objects())
    assert first.value(x) == expected[0]


def test_the_key_reads_the_code_without_its_comments_layout_and_docstrings(tmp_path, monkeypatch):
    """A docstring, a comment or the layout changed: the same digest, so kept programs stay; any change to what
    runs (a constant, an operator, a string that is not a docstring, a comprehension's constant) is another.
    The bytecode Python keeps beside a file gives the digest its text gives."""
    import os
    import py_compile
    import sys

    source = b'''"""A module."""
import math


def f(x, a=2.0):
    """Twice x."""
    return a * x + math.pi  # a comment


def g(y):
    return [str(v) + "q" for v in y], "text"
'''

    def digest(text: bytes) -> str:
        path = tmp_path / f"m{abs(hash(text))}.py"
        path.write_bytes(text)
        return programs.file_digest(path, text)

    base = digest(source)
    same = [source.replace(b"Twice x.", b"Two times x, see (4.36)."), source.replace(b"# a comment", b"# another"),
            source.replace(b"return a * x", b"return (a\n            * x)"), b"\n\n" + source]
    changed = [source.replace(b"a=2.0", b"a=3.0"), source.replace(b"a * x", b"a / x"),
               source.replace(b"math.pi", b"math.e"), source.replace(b'"q"', b'"r"'),
               source.replace(b'"text"', b'"other"')]
    if sys.version_info[:2] in programs.DOCSTRING_FIRST:
        assert [digest(s) for s in same] == [base] * len(same)
    assert len({base, *(digest(s) for s in changed)}) == len(changed) + 1
    # From the bytecode kept beside the file (written after it), the same digest.
    path = tmp_path / "kept.py"
    path.write_bytes(source)
    earlier = path.stat().st_mtime_ns - 2 * 10**9
    os.utime(path, ns=(earlier, earlier))  # the text older than the bytecode, whatever the clock's grain
    py_compile.compile(str(path))
    with monkeypatch.context() as reading:
        reading.setattr(programs, "compile", lambda *args, **kwargs: pytest.fail("compiled"), raising=False)
        kept = programs.compiled_code(path, source)
    assert programs.hashlib.sha256(programs.code_digest(kept)).hexdigest() == base
    # Bytes that the file no longer holds (read before a change): compiled from them, not read from the bytecode.
    other = changed[0]
    assert programs.hashlib.sha256(programs.code_digest(programs.compiled_code(path, other))).hexdigest() == \
        digest(other)


def test_the_code_digests_are_remembered_and_a_damaged_record_is_computed_again(tmp_path, monkeypatch):
    """The first process computes greyid's files' digests and keeps them; a later one reads them (the same
    key), and a damaged record is computed again and written anew."""
    monkeypatch.setenv("GREYID_CACHE_DIR", "off")
    expected = programs.source_hash.__wrapped__()  # no folder: every file's digest computed
    monkeypatch.setenv("GREYID_CACHE_DIR", str(tmp_path))
    record = tmp_path / "programs" / programs.CODE_DIGESTS
    assert programs.source_hash.__wrapped__() == expected
    written = record.read_bytes()
    with monkeypatch.context() as computing:
        computing.setattr(programs, "file_digest", lambda *args: pytest.fail("computed a remembered digest"))
        assert programs.source_hash.__wrapped__() == expected
    assert record.read_bytes() == written  # nothing new: not written again
    record.write_bytes(written[:-1] + bytes([written[-1] ^ 1]))
    assert programs.source_hash.__wrapped__() == expected
    programs.unseal(record.read_bytes())  # sound again
    assert programs.usage()["programs"] == (0, 0)  # the record is not a program
