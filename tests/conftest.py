"""Shared models and references for the tests (compiled once per session)."""

from __future__ import annotations

import os

# Data sets named in model files and examples (greyid.datasets.fetch) are read from the project's
# shared/data beside the checkout, where it is, instead of downloaded.
_SHARED_DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")
if os.path.isdir(_SHARED_DATA):
    os.environ.setdefault("GREYID_DATA_MIRROR", os.path.abspath(_SHARED_DATA))

# One cache folder for the tests, of their own (the user's cache folder is neither read nor written),
# holding both what greyid keeps of a program: its traced program (greyid.runtime.store, on as for a
# user; the file's name hashes greyid's code, so that a change to it, not to a comment, traces anew) and XLA's
# compilation of it (JAX's persistent cache).  Tracing and compiling are most of a test's time, and
# the same program is made again and again — by tests that build the same model anew, in a module
# after an earlier one's programs were released (_release_memory), in the command line's and Dask's
# worker processes (which inherit these variables), and in the next run.  Every program is kept,
# however quickly it compiled (JAX keeps only those of a second or more by default).  The folder is
# kept between runs (GREYID_TEST_CACHE, default ~/.cache/greyid/tests), so that a later run traces and
# compiles only the programs a change made new: both keys name the program's whole content, so a kept
# program is the one tracing and XLA would give.  A test that replaces part of greyid at run time
# (the monkeypatch fixture below) keeps and loads no traced program.  A run starts by pruning the
# folder to TEST_CACHE_BYTES, the oldest files first (JAX's own limit would scan the folder at every
# program it keeps).  GREYID_TEST_CACHE=run keeps them for the run only, in a folder removed at exit,
# as on a clean machine.
TEST_CACHE_BYTES = 4 * 10**9


def prune_oldest(folder: str, limit: int) -> None:
    """Remove the oldest files of ``folder`` and its subfolders until they hold at most ``limit`` bytes."""
    kept = []
    for parent, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(parent, name)
            try:
                status = os.stat(path)
            except OSError:  # removed meanwhile
                continue
            kept.append((status.st_mtime, status.st_size, path))
    total = sum(size for _, size, _ in kept)
    for _, size, path in sorted(kept):
        if total <= limit:
            break
        try:
            os.remove(path)
        except OSError:
            pass
        total -= size


if "GREYID_CACHE_DIR" not in os.environ:  # the first process of the run (test workers inherit it)
    import atexit
    import shutil
    import tempfile

    _KEPT = os.environ.get("GREYID_TEST_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "greyid", "tests"))
    if _KEPT == "run":
        _KEPT = tempfile.mkdtemp(prefix="greyid-tests-")
        atexit.register(shutil.rmtree, _KEPT, True)
    else:
        os.makedirs(_KEPT, exist_ok=True)
        prune_oldest(_KEPT, TEST_CACHE_BYTES)
    os.environ["GREYID_CACHE_DIR"] = _KEPT
    # The lock files by which a test marked "alone" runs while no other test does (taking_turns below).
    _TURNS = tempfile.mkdtemp(prefix="greyid-test-turns-")
    atexit.register(shutil.rmtree, _TURNS, True)
    os.environ["GREYID_TEST_TURNS"] = _TURNS
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

# greyid (with JAX) and SciPy are imported where a helper or fixture needs them, not here: pytest-xdist's
# controller process loads this file too and runs no test, and would hold them (about 0.3 GB) all run long.
import contextlib  # noqa: E402
import functools  # noqa: E402
from typing import TYPE_CHECKING  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

if TYPE_CHECKING:
    import greyid


def random_linear_model_spec(n=3, nu=2, ny=2, nw=2):
    """Equations of a general linear model with every coefficient a parameter."""
    import greyid

    m = greyid.Model(f"linear{n}{nu}{ny}{nw}")
    for i in range(1, n + 1):
        drift = " + ".join([f"a{i}{j}*x{j}" for j in range(1, n + 1)]
                           + [f"b{i}{j}*u{j}" for j in range(1, nu + 1)] + [f"c{i}"])
        noise = " + ".join(f"g{i}{j}*dw{j}" for j in range(1, nw + 1))
        m.add_system(f"dx{i} = ({drift})*dt + {noise}")
    m.add_inputs(*[f"u{j}" for j in range(1, nu + 1)])
    for i in range(1, ny + 1):
        obs = " + ".join([f"h{i}{j}*x{j}" for j in range(1, n + 1)] + [f"d{i}1*u1"])
        m.add_observation(f"y{i} = {obs}", variance=f"s{i}")
    cov = [[f"v{min(i, j)}{max(i, j)}" for j in range(1, n + 1)] for i in range(1, n + 1)]
    m.set_initial_state(mean={f"x{i}": f"m{i}" for i in range(1, n + 1)}, covariance=cov)
    return m


def random_linear_parameters(rng, n=3, nu=2, ny=2, nw=2):
    """Random stable A, inputs, noise and observation matrices, as a parameter dict."""
    eig = -rng.uniform(0.2, 2.0, n)
    V = rng.normal(size=(n, n)) + 2 * np.eye(n)
    A = V @ np.diag(eig) @ np.linalg.inv(V)
    B, c = rng.normal(size=(n, nu)), rng.normal(size=n)
    G, H, D = rng.normal(size=(n, nw)) * 0.5, rng.normal(size=(ny, n)), rng.normal(size=(ny, 1))
    S = rng.uniform(0.05, 0.3, ny)
    M = rng.normal(size=(n, n))
    P0 = M @ M.T + 0.5 * np.eye(n)
    m0 = rng.normal(size=n)
    p = {}
    for i in range(n):
        p[f"c{i + 1}"] = c[i]
        p[f"m{i + 1}"] = m0[i]
        for j in range(n):
            p[f"a{i + 1}{j + 1}"] = A[i, j]
            if j >= i:
                p[f"v{i + 1}{j + 1}"] = P0[i, j]
        for j in range(nu):
            p[f"b{i + 1}{j + 1}"] = B[i, j]
        for j in range(nw):
            p[f"g{i + 1}{j + 1}"] = G[i, j]
    for i in range(ny):
        p[f"s{i + 1}"] = S[i]
        p[f"d{i + 1}1"] = D[i, 0]
        for j in range(n):
            p[f"h{i + 1}{j + 1}"] = H[i, j]
    mats = dict(A=A, B=B, c=c, G=G, H=H, D=D, S=S, P0=P0, m0=m0)
    return p, mats


def van_loan(A, Q, tau):
    """Φ, ∫e^{As}ds, (1/τ)∫e^{As}(τ−s)ds and Λ by plain block exponentials (SciPy).

    Kept by (A, Q, τ): a dense reference evaluated at many parameter values (finite differences of a
    dense likelihood) asks for the same intervals' discretization each time its A and Q stay.
    """
    A, Q = np.asarray(A, dtype=float), np.asarray(Q, dtype=float)
    parts = _van_loan(A.shape[0], A.tobytes(), Q.tobytes(), float(tau))
    return tuple(part.copy() for part in parts)


@functools.lru_cache(maxsize=8192)
def _van_loan(n, A_bytes, Q_bytes, tau):
    import scipy.linalg as sl

    A = np.frombuffer(A_bytes).reshape(n, n)
    Q = np.frombuffer(Q_bytes).reshape(n, n)
    Z, I = np.zeros((n, n)), np.eye(n)
    E = sl.expm(np.block([[A, I, Z], [Z, Z, I], [Z, Z, Z]]) * tau)
    F = sl.expm(np.block([[-A, Q], [Z, A.T]]) * tau)
    ups = E[:n, 2 * n:] / tau if tau > 0 else np.zeros((n, n))
    return E[:n, :n], E[:n, n:2 * n], ups, F[n:, n:].T @ F[:n, n:]


def dense_moments(mats, t, U, foh):
    """Mean and covariance of the stacked states and observations, from the discretized model."""
    import scipy.linalg as sl

    A, B, c, G, H, D, S = (mats[k] for k in "A B c G H D S".split())
    N, n = len(t), A.shape[0]
    b = U @ B.T + c  # affine drift term at each row
    # X = mean + T w, w = (x0 - m0, w_1, ..., w_{N-1})
    trans, shift, noise = [np.eye(n)], [np.zeros(n)], [mats["P0"]]
    for k in range(1, N):
        phi, gam, ups, lam = van_loan(A, G @ G.T, t[k] - t[k - 1])
        trans.append(phi)
        shift.append(gam @ b[k - 1] + foh * ups @ (b[k] - b[k - 1]))
        noise.append(lam)
    mean = np.zeros((N, n))
    mean[0] = mats["m0"]
    for k in range(1, N):
        mean[k] = trans[k] @ mean[k - 1] + shift[k]
    T = np.zeros((N * n, N * n))
    for k in range(N):
        block = np.eye(n)
        for j in range(k, -1, -1):
            T[k * n:(k + 1) * n, j * n:(j + 1) * n] = block
            block = block @ trans[j]
    Xcov = T @ sl.block_diag(*noise) @ T.T
    Hbig = np.kron(np.eye(N), H)
    ymean = (mean @ H.T + U[:, :1] @ D.T).reshape(-1)
    ycov = Hbig @ Xcov @ Hbig.T + np.diag(np.tile(S, N))
    return mean, Xcov, Hbig, ymean, ycov


def dense_reference(mats, t, U, Y, foh):
    """Log-density of the observed elements, and the smoothed states E[X | y], Cov[X | y].

    Built from the mean and covariance of all stacked observations (:func:`dense_moments`).
    """
    from scipy.stats import multivariate_normal

    mean, Xcov, Hbig, ymean, ycov = dense_moments(mats, t, U, foh)
    obs = ~np.isnan(Y.reshape(-1))
    ll = multivariate_normal(ymean[obs], ycov[np.ix_(obs, obs)]).logpdf(Y.reshape(-1)[obs])
    K = Xcov @ Hbig[obs].T @ np.linalg.inv(ycov[np.ix_(obs, obs)])
    xs = mean.reshape(-1) + K @ (Y.reshape(-1)[obs] - ymean[obs])
    Ps = Xcov - K @ Hbig[obs] @ Xcov
    return ll, xs.reshape(xs.shape[0] // mean.shape[1], mean.shape[1]), Ps


def matrices_from_parameters(p, n=3, nu=2, ny=2, nw=2):
    """The matrices of :func:`random_linear_model_spec` at the parameter dict ``p``."""
    A = np.array([[p[f"a{i}{j}"] for j in range(1, n + 1)] for i in range(1, n + 1)])
    B = np.array([[p[f"b{i}{j}"] for j in range(1, nu + 1)] for i in range(1, n + 1)])
    G = np.array([[p[f"g{i}{j}"] for j in range(1, nw + 1)] for i in range(1, n + 1)])
    H = np.array([[p[f"h{i}{j}"] for j in range(1, n + 1)] for i in range(1, ny + 1)])
    P0 = np.array([[p[f"v{min(i, j)}{max(i, j)}"] for j in range(1, n + 1)] for i in range(1, n + 1)])
    return dict(A=A, B=B, c=np.array([p[f"c{i}"] for i in range(1, n + 1)]), G=G, H=H,
                D=np.array([[p[f"d{i}1"]] for i in range(1, ny + 1)]),
                S=np.array([p[f"s{i}"] for i in range(1, ny + 1)]), P0=P0,
                m0=np.array([p[f"m{i}"] for i in range(1, n + 1)]))


def product_model(init: dict, lower=None) -> greyid.Model:
    """dx = (−a·b·x + u)dt + s dω, y = x + e: the output depends on a and b only through a·b."""
    import greyid

    m = greyid.Model("product")
    m.add_system("dx = (-a*b*x + u)*dt + s*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[0.1]])
    for name, value in init.items():
        m.set_parameter(name, init=value, lower=lower)
    return m


def dense_information(params, t, U, names, foh=0.0):
    """Fisher information of all stacked observations of :func:`random_linear_model_spec`,
    ∂μᵀΣ⁻¹∂μ + ½tr(Σ⁻¹∂ΣΣ⁻¹∂Σ), with ∂μ and ∂Σ by central differences of :func:`dense_moments`."""
    d_mean, d_cov = [], []
    for name in names:
        h = 1e-5 * max(abs(params[name]), 1.0)
        up = dense_moments(matrices_from_parameters(dict(params, **{name: params[name] + h})), t, U, foh)
        down = dense_moments(matrices_from_parameters(dict(params, **{name: params[name] - h})), t, U, foh)
        d_mean.append((up[3] - down[3]) / (2 * h))
        d_cov.append((up[4] - down[4]) / (2 * h))
    inv = np.linalg.inv(dense_moments(matrices_from_parameters(params), t, U, foh)[4])
    k = len(names)
    return np.array([[d_mean[i] @ inv @ d_mean[j] + 0.5 * np.trace(inv @ d_cov[i] @ inv @ d_cov[j])
                      for j in range(k)] for i in range(k)])


@pytest.fixture(scope="session")
def linear_model():
    return random_linear_model_spec()


@pytest.fixture(scope="session")
def building():
    from greyid.datasets import TRUE_PARAMETERS, building_model, load_building_data

    return building_model(), TRUE_PARAMETERS, load_building_data()


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``greyid demo --out DIR`` run once: (exit code, printed text, output folder)."""
    import contextlib
    import io

    from greyid.cli import main

    folder = tmp_path_factory.mktemp("demo")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["demo", "--out", str(folder), "--quiet"])
    return code, printed.getvalue(), folder


@pytest.fixture
def monkeypatch(monkeypatch, request):
    """pytest's ``monkeypatch``, whose ``setattr``, ``setitem``, ``delattr`` and ``delitem`` first switch
    greyid's kept traced programs off for the test (``GREYID_PROGRAMS=off``): what a test replaces (a
    function, a constant) changes programs whose keys do not name it ([`greyid.runtime.store`][greyid.runtime.store]),
    so such a test neither loads a program traced without its change nor keeps one traced with it.  A
    test that only changes folder or environment keeps them, and one marked ``own_program_store``
    (test_store.py) sets the store itself."""
    if request.node.get_closest_marker("own_program_store"):
        return monkeypatch
    plain = {name: getattr(monkeypatch, name) for name in ("setattr", "setitem", "delattr", "delitem")}

    def switching_off(name):
        def replace(*args, **kwargs):
            # setenv and delenv go through setitem and delitem on os.environ: an environment changes no program
            if not (name.endswith("item") and args and args[0] is os.environ):
                monkeypatch.setenv("GREYID_PROGRAMS", "off")
            return plain[name](*args, **kwargs)
        return replace

    for name in plain:  # on this test's instance only (pytest makes one per test)
        vars(monkeypatch)[name] = switching_off(name)
    return monkeypatch


@pytest.fixture
def compilations(monkeypatch):
    """The programs greyid compiles during the test, each as lowered: every one goes through
    ``greyid.runtime.jit.compile_lowered``, which passes greyid's XLA options."""
    from greyid.runtime import jit

    seen = []
    real = jit.compile_lowered

    def recording(lowered):
        seen.append(lowered)
        return real(lowered)

    monkeypatch.setattr(jit, "compile_lowered", recording)
    return seen


def release_memory(models_too: bool = False) -> None:
    """Drop the programs JAX keeps for the functions it traced, collect, and hand the freed heap back;
    ``models_too``: also those the models still alive keep (release_compiled()), which a later call of
    theirs loads again from the cache folder (seconds for a population's)."""
    import gc

    import jax

    if models_too:
        from greyid.runtime.jit import release_compiled

        release_compiled()  # JAX's caches with them
    else:
        jax.clear_caches()
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to hand back this way
        pass


#: Resident memory (GiB) above which a test's programs are released at its end rather than at its module's:
#: the few modules whose programs are large (nested derivatives of population fits) would otherwise hold
#: each test's on top of the last; below it a module's tests share what JAX traced.  With the traced programs
#: kept (the store), a released program comes back from the folder rather than being traced again.
RELEASE_ABOVE_GIB = 1.6


@pytest.fixture(autouse=True)
def _release_memory_after_a_large_test():
    """After a test that leaves its process above RELEASE_ABOVE_GIB, release what JAX keeps (release_memory)."""
    yield
    if _resident_gib() > RELEASE_ABOVE_GIB:
        release_memory()


@pytest.fixture(scope="module", autouse=True)
def _release_memory(request):
    """After each test module, drop the programs JAX keeps for the functions it traced and hand
    the freed heap back to the system: the suite runs in one process, and glibc keeps what XLA's
    compiler freed unless asked (``malloc_trim``), so without it the process grows module by module.
    ``GREYID_TEST_MEMORY_LOG=FILE`` appends each module's seconds and resident memory (GiB) before
    and after."""
    import time

    started = time.monotonic()
    yield
    before = _resident_gib()
    release_memory(models_too=True)
    log = os.environ.get("GREYID_TEST_MEMORY_LOG")
    if log:
        compiling = {name: _COMPILE_SECONDS.pop(event, 0.0) for event, name in _COMPILE_EVENTS.items()}
        with open(log, "a") as out:
            out.write(f"{request.module.__name__} {time.monotonic() - started:.1f} s {before:.2f} "
                      f"{_resident_gib():.2f} "
                      + " ".join(f"{name}={seconds:.1f}" for name, seconds in compiling.items())
                      + "\n")


# JAX's own timings of the three steps of a compilation (jax.monitoring, a public API), summed
# per module for GREYID_TEST_MEMORY_LOG: where the suite's time goes.
_COMPILE_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "xla",
}
_COMPILE_SECONDS: dict[str, float] = {}


def _count_compile_seconds(event: str, duration: float, **_: object) -> None:
    if event in _COMPILE_EVENTS:
        _COMPILE_SECONDS[event] = _COMPILE_SECONDS.get(event, 0.0) + duration


if os.environ.get("GREYID_TEST_MEMORY_LOG"):
    import jax.monitoring  # noqa: E402

    jax.monitoring.register_event_duration_secs_listener(_count_compile_seconds)


def _resident_gib() -> float:
    """This process's resident memory in GiB (0 where /proc is not there)."""
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**30
    except OSError:
        return 0.0


#: Physical memory from which the suite runs in two worker processes (``-n auto`` in pyproject.toml):
#: in two, the suite's processes together peak at 3.4–3.5 GiB on a later run, 3.9–4.0 GiB on one that traces every
#: program again (docs/install.md).
TWO_WORKERS_MEMORY = 12 * 2**30


def pytest_xdist_auto_num_workers(config) -> int:
    """Two test workers where the machine has two cores or more and TWO_WORKERS_MEMORY, else one."""
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not a POSIX system that says: one worker
        memory = 0
    return 2 if (os.cpu_count() or 1) >= 2 and memory >= TWO_WORKERS_MEMORY else 1


@contextlib.contextmanager
def taking_turns(folder: str, alone: bool, waiting=None):
    """Run the block while no other block runs (``alone``) or beside other blocks that are not alone,
    across processes: every block holds a shared lock on ``folder``/turns, an ``alone`` block an exclusive
    one.  ``folder``/gate is held by an ``alone`` block while it waits, so that no block starts meanwhile
    (else two processes could take turns and keep it waiting for good); a block that finds the gate held,
    or an ``alone`` block running, calls ``waiting()`` (once) before it waits."""
    import fcntl

    told = []

    def take(file, lock):
        try:
            fcntl.flock(file, lock | fcntl.LOCK_NB)
        except BlockingIOError:
            if waiting is not None and not told:
                told.append(True)
                waiting()
            fcntl.flock(file, lock)

    with open(os.path.join(folder, "gate"), "a") as gate, open(os.path.join(folder, "turns"), "a") as turns:
        take(gate, fcntl.LOCK_EX)
        if alone:
            fcntl.flock(turns, fcntl.LOCK_EX)  # once the blocks that run have ended
        fcntl.flock(gate, fcntl.LOCK_UN)
        if not alone:
            take(turns, fcntl.LOCK_SH)  # at once, unless an alone block runs
        yield  # the locks end with the files


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """A test marked ``alone`` (one that starts worker processes of its own, a Dask cluster, or whose programs
    take gigabytes) runs while the other test worker waits between its tests, both with their programs
    released, so that the memory of the run's processes together stays low (taking_turns: for the test's
    setup, call and teardown, its fixtures' too).  Without the folder (GREYID_TEST_TURNS, made by the run's
    first process) tests run as they come."""
    folder = os.environ.get("GREYID_TEST_TURNS")
    if not folder or not os.path.isdir(folder):
        yield
        return
    alone = item.get_closest_marker("alone") is not None
    with taking_turns(folder, alone, waiting=functools.partial(release_memory, models_too=True)):
        if alone:  # its worker processes make their own programs: this one's can go meanwhile
            release_memory(models_too=True)
        yield
