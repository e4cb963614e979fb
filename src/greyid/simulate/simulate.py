"""Sample paths of a model's states and noisy observations (section 2.5).

``model.simulate(params, data_or_times, n_paths, method, seed)`` takes the
sampling times (and inputs) from a DataFrame, or plain times for a model
without inputs.  Between sampling times each path takes ``substeps`` steps of
the chosen scheme, with inputs held (``hold="zoh"``) or interpolated
(``hold="foh"``).  ``method="exact"`` samples a time-invariant linear model exactly from its
discretization (4.34–4.39), and a time-varying one from ``substeps`` midpoint
pieces per interval (second order, as its Kalman filter).  The initial state is drawn from N(x0, P0).
"""

from __future__ import annotations

import os

from dataclasses import dataclass

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ..data.prepare import Series, check_times, prepare_series
from ..runtime.jit import jit, structure_program
from ..errors import DataError, ModelError
from ..filters.api import HOLDS, filter_inputs
from ..filters.gaussian import initial_state
from ..filters.delays import check_delays, delays_at, values_at
from ..filters.discretize import discretize, time_varying_step
from ..model.distributions import moments, sample
from ..model.structure import LTI
from ..model.transforms import paths_to_original
from .schemes import make_integrator

METHODS = ("euler", "milstein", "heun", "exact")


@dataclass(frozen=True)
class Simulation:
    """Simulated paths: ``states`` (paths, N, n) and ``outputs`` (paths, N, s)."""

    times: np.ndarray
    inputs: np.ndarray
    states: np.ndarray
    outputs: np.ndarray
    time_name: str
    input_names: tuple[str, ...]
    state_names: tuple[str, ...]
    output_names: tuple[str, ...]
    #: The model's latent forces ([`LatentForce`][greyid.model.latent.LatentForce]): a force that is not itself
    #: a state (a composite kernel's) is a column of its own in ``frame``.
    latent_forces: tuple = ()

    @property
    def n_paths(self) -> int:
        return self.states.shape[0]

    def frame(self, path: int = 0) -> pd.DataFrame:
        """One path as a DataFrame with time, inputs, states and outputs (ready to filter).

        Parameters
        ----------
        path : int
            Which path.

        Returns
        -------
        pandas.DataFrame
            The path.
        """
        cols = {self.time_name: self.times}
        cols.update({n: self.inputs[:, j] for j, n in enumerate(self.input_names)})
        cols.update({n: self.states[path, :, j] for j, n in enumerate(self.state_names)})
        cols.update({f.name: f.values(self.states[path])[0] for f in self.latent_forces
                     if f.name not in self.state_names})
        cols.update({n: self.outputs[path, :, j] for j, n in enumerate(self.output_names)})
        return pd.DataFrame(cols)

    def to_frame(self) -> pd.DataFrame:
        """All paths stacked, with a ``path`` column.

        Returns
        -------
        pandas.DataFrame
            The paths.
        """
        return pd.concat([self.frame(p).assign(path=p) for p in range(self.n_paths)], ignore_index=True)


def _series(structure, data_or_times, time, time_unit):
    if isinstance(data_or_times, pd.DataFrame):
        return prepare_series(data_or_times, structure.input_names, structure.output_names, time, time_unit,
                              require_outputs=False)
    times = np.asarray(data_or_times, dtype=np.float64)
    if times.ndim != 1 or len(times) == 0:
        raise DataError("times must be a non-empty one-dimensional array")
    if structure.n_inputs:
        raise DataError(f"the model has inputs {list(structure.input_names)}; pass a DataFrame holding them")
    check_times(times, time)
    return Series(times, np.zeros((len(times), 0)), np.full((len(times), structure.n_outputs), np.nan),
                  pd.RangeIndex(len(times)), time)


def delayed_grid(structure, theta, series, hold: str):
    """``(grid, rows)``: the series refined at every delayed switching instant t_j + τ, its
    inputs extended with the delayed ones, and the positions of the sampling times in it."""
    if not structure.delays:
        return series, np.arange(series.n_rows)
    check_delays(structure, theta, series.times)
    t = series.times
    delays = delays_at(structure, theta, t, series.inputs, jnp.float64(HOLDS[hold]))
    cuts = (t[:, None] + np.asarray(delays.taus)[None, :]).reshape(-1)
    times = np.unique(np.concatenate([t, cuts[(cuts > t[0]) & (cuts < t[-1])]]))
    # A held input's value on [T_i, T_i+1) is read at the interval's middle: at T_i itself a
    # switching instant t_j + τ may round to either side of t_j.
    at = times if hold == "foh" else np.concatenate([0.5 * (times[:-1] + times[1:]), times[-1:]])
    if hold == "foh":
        own = np.stack([np.interp(times, t, column) for column in series.inputs.T], axis=1)
    else:
        own = series.inputs[np.clip(np.searchsorted(t, at, side="right") - 1, 0, len(t) - 1)]
    inputs = np.concatenate([own, np.asarray(values_at(delays, at))], axis=1)
    grid = Series(times, inputs, np.full((len(times), structure.n_outputs), np.nan), pd.RangeIndex(len(times)),
                  series.time_name)
    return grid, np.searchsorted(times, t)


def _fine_grid(series, substeps: int, hold: str):
    """Times and inputs on the grid of ``substeps`` steps per sampling interval."""
    t = series.times
    frac = np.arange(substeps) / substeps
    fine_t = np.concatenate([(t[:-1, None] + np.diff(t)[:, None] * frac).reshape(-1), t[-1:]])
    u = series.inputs
    if hold == "foh":
        fine_u = np.concatenate([(u[:-1, None, :] + np.diff(u, axis=0)[:, None, :] * frac[None, :, None])
                                 .reshape(-1, u.shape[1]), u[-1:]])
    else:
        fine_u = np.concatenate([np.repeat(u[:-1], substeps, axis=0), u[-1:]])
    return fine_t, fine_u


def simulate(model, params, data_or_times, n_paths: int = 1, method: str = "euler", seed: int = 0,
             substeps: int = 10, hold: str = "zoh", calculus: str = "ito", time: str = "t",
             time_unit: str | None = None, noise: bool = True) -> Simulation:
    """Seeded, reproducible sample paths of a model's states and noisy observations (section 2.5).

    Parameters
    ----------
    model : Model
        The model.
    params : mapping of str to float
        The parameters' values.
    data_or_times : pandas.DataFrame or array_like
        The times and the inputs, or the times alone for a model without inputs.
    n_paths : int
        The number of paths.
    method : {"euler", "milstein", "heun", "exact"}
        The scheme (``"exact"``: the exact discretisation of a linear model).
    seed : int
        The random seed.
    substeps : int
        Integration steps per sampling interval.
    hold : {"zoh", "foh"}
        How inputs are held between samples.
    calculus : {"ito", "stratonovich"}
        The stochastic calculus the equations are written in.
    time : str
        The name of the time column.
    time_unit : str, optional
        The unit of elapsed time for timestamps.
    noise : bool
        False: the deterministic part alone (the ODE from the initial mean, no
        process or observation noise), the model's simulation of the measured
        outputs (section 5.3).

    Returns
    -------
    Simulation
        ``frame(i)``: the i-th path as a DataFrame (time, inputs, states, outputs);
        ``to_frame()``: all paths with a ``path`` column.
    """
    structure = model.structure
    if method not in METHODS:
        raise ModelError(f"unknown simulation method '{method}'; use one of {list(METHODS)}")
    if hold not in HOLDS:
        raise DataError(f"unknown hold '{hold}'; use 'zoh' or 'foh'")
    if not isinstance(n_paths, int) or n_paths < 1:
        raise ModelError(f"n_paths must be a positive integer, got {n_paths!r}")
    if not isinstance(substeps, int) or substeps < 1:
        raise ModelError(f"substeps must be a positive integer, got {substeps!r}")
    if calculus == "stratonovich" and structure.state_transforms:
        raise ModelError("the model's transformed states were rewritten by Itô's formula: its equations are Itô "
                         "equations; simulate it with calculus='ito'")
    if method == "exact" and not noise and structure.ode_drift is not None:
        raise ModelError("noise=False follows dx = f dt, whose drift in the transformed states' coordinates is not "
                         "the linear drift the exact scheme solves (Itô's term belongs to the noise); use "
                         "method='heun' or 'euler'")
    if method == "exact" and not structure.is_linear:
        raise ModelError(f"exact simulation needs a linear model, but this model is {structure.kind}")
    theta = jnp.asarray(model.parameter_vector(params))
    series = _series(structure, data_or_times, time, time_unit)
    # With delayed inputs the paths run on a grid refined at the delayed switching instants,
    # so that every input is held (or ramped) over each of its intervals; ``rows`` picks the
    # sampling times out of it.
    grid, rows = delayed_grid(structure, theta, series, hold)
    inputs = filter_inputs(grid, hold)
    start = structure_program(structure, ("simulate", "initial"),
                              lambda: lambda theta, inputs: initial_state(structure, theta, inputs))
    x0, P0 = start(theta, inputs)
    n, m = structure.n_states, len(structure.noise_names)
    scale = 1.0 if noise else 0.0
    if method == "exact":
        path_shape = (n_paths, len(grid.times) - 1, n)
    else:
        fine_t, fine_u = _fine_grid(grid, substeps, hold)
        path_shape = (n_paths, len(fine_t) - 1, m)
    check_memory(n_paths, path_shape[1], max(m, n) + 2 * n, len(series.times), 4 * structure.n_outputs + 2 * n)
    init, path_noise, z = _draws(jax.random.PRNGKey(seed), x0, P0, scale, path_shape,
                                 (n_paths, len(series.times), structure.n_outputs))

    if method == "exact":
        states = _exact_paths(structure, theta, grid, HOLDS[hold], init, path_noise, substeps)
    else:
        # Without noise the paths solve the ODE dx = f dt: the Itô–Stratonovich and
        # Milstein corrections belong to the noise and must go with it.
        diffusion = structure.diffusion if noise else _no_diffusion(m)
        # A transformed state's drift holds Itô's term, which belongs to the noise as well.
        drift = structure.drift if noise or structure.ode_drift is None else structure.ode_drift
        integrate = structure_program(structure, ("simulate", method, calculus, bool(noise)),
                                      lambda: jax.vmap(make_integrator(drift, diffusion, method, calculus),
                                                       in_axes=(None, 0, None, None, 0)))
        dW = np.asarray(path_noise) * np.sqrt(np.diff(fine_t))[None, :, None]
        fine = integrate(theta, init, jnp.asarray(fine_t), jnp.asarray(fine_u), dW)
        states = np.asarray(fine)[:, ::substeps, :]
    states = states[:, rows, :]

    u, t = jnp.asarray(grid.inputs[rows]), jnp.asarray(series.times)
    observe = structure_program(structure, ("simulate", "observe"), lambda: _make_observe(structure))
    y_mean, S = (np.asarray(a) for a in observe(theta, jnp.asarray(states), u, t))
    if np.any(S < 0):
        raise ModelError("an observation variance is negative along the simulated paths")
    z = np.asarray(z)
    if structure.distributions:  # counts and other non-Gaussian outputs: drawn from their distributions
        draw = structure_program(structure, ("simulate", "distributions", bool(noise)),
                                 lambda: _make_draw(structure, bool(noise)))
        y = np.asarray(draw(theta, jnp.asarray(states), u, t, jax.random.fold_in(jax.random.PRNGKey(seed), 1)))
    elif structure.observation_covariance is None:
        y = y_mean + scale * np.sqrt(S) * z
    else:  # correlated measurement noise: e = L z with L Lᵀ = S (S free of the states)
        full = jax.vmap(lambda uu, tt: structure.observation_covariance(jnp.zeros(n), uu, tt, theta))(u, t)
        y = y_mean + scale * jnp.einsum("kij,pkj->pki", jnp.linalg.cholesky(full), z)
    states = paths_to_original(structure.state_transforms, np.asarray(theta), np.asarray(states))
    return Simulation(series.times, series.inputs, states, np.asarray(y), series.time_name,
                      structure.input_names, structure.state_names, structure.output_names,
                      structure.latent_forces)


def available_memory() -> int | None:
    """Bytes of memory available now (Linux, macOS), or None where it cannot be told."""
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(n_paths: int, steps: int, per_step: int, rows: int, per_row: int) -> None:
    """Refuse a simulation whose arrays (float64: ``per_step`` numbers per integration step and path,
    ``per_row`` per sampling time and path) would not fit in the memory available, before any is made."""
    need = 8 * n_paths * (steps * per_step + rows * per_row)
    available = available_memory()
    if available is not None and need > 0.8 * available:
        raise ModelError(f"{n_paths} paths of {rows} rows ({steps} integration steps each) need about "
                         f"{need / 1e9:.3g} GB, more than the {available / 1e9:.3g} GB of memory available: "
                         "simulate fewer paths at a time (several calls with different seeds)")


def _no_diffusion(m: int):
    def diffusion(x, u, t, theta):
        return jnp.zeros((x.shape[0], m))

    return diffusion


def _along_paths(fn, theta, states, u, t):
    """``fn(x, u, t, θ)`` at every path's state of every row (paths, N, ...)."""
    return jax.vmap(jax.vmap(lambda x, uu, tt: fn(x, uu, tt, theta)), in_axes=(0, None, None))(states, u, t)


def _make_observe(structure):
    """Means and variances of the observations along paths (paths, N, outputs)."""
    def observe(theta, states, u, t):
        return (_along_paths(structure.observation, theta, states, u, t),
                _along_paths(structure.observation_variance, theta, states, u, t))

    return observe


def _make_draw(structure, noise: bool):
    """Observations drawn from their distributions along paths (paths, N, outputs), or without
    ``noise`` their means ([`distributions`][greyid.model.distributions])."""
    def draw(theta, states, u, t, key):
        m, S, a = _along_paths(structure.observation_law, theta, states, u, t)
        columns = []
        for j, family in enumerate(structure.output_families):
            if noise:
                columns.append(sample(family, jax.random.fold_in(key, j), m[..., j], S[..., j], a[..., j]))
            else:
                columns.append(moments(family, m[..., j], S[..., j], a[..., j])[0])
        return jnp.stack(columns, axis=-1)

    return draw


def _draw(key, x0, P0, scale, path_shape, observation_shape):
    """The paths' random numbers, in one program (drawn one by one, each would be a program
    to trace in every process): initial states x0 + P0^½ z, the paths' standard normals
    times ``scale`` and the observations' standard normals."""
    k_init, k_path, k_obs = jax.random.split(key, 3)
    init = x0 + scale * jax.random.normal(k_init, (path_shape[0], x0.shape[0])) @ _psd_sqrt(P0).T
    return init, scale * jax.random.normal(k_path, path_shape), jax.random.normal(k_obs, observation_shape)


_draws = jit(_draw, static_argnums=(4, 5))


def _psd_sqrt(P):
    """A square root of a positive semi-definite matrix (eigenvalues clipped at 0)."""
    w, V = jnp.linalg.eigh(0.5 * (P + P.T))
    return V * jnp.sqrt(jnp.clip(w, 0.0, None))[None, :]


def _exact_paths(structure, theta, series, foh, init, z, substeps=10):
    """x_{k+1} = Φx_k + Γb_k + Υ(b_{k+1} − b_k) + Λ^½ z_k for linear models.

    Exact for time-invariant models; a time-varying model's Φ, offset and Λ come
    from ``substeps`` midpoint pieces per interval, as in its Kalman filter.
    """
    varying = structure.kind != LTI
    run = structure_program(structure, ("simulate", "exact", substeps if varying else 1),
                            lambda: _make_exact(structure, substeps if varying else None))
    return np.asarray(run(theta, jnp.asarray(series.times), jnp.asarray(series.inputs), foh, init, z))


def _make_exact(structure, substeps: int | None):
    f, G = structure.drift, structure.diffusion
    zeros = jnp.zeros(structure.n_states)
    jac = jax.jacfwd(f, argnums=0)

    def paths(theta, t, u, foh, init, z):
        def interval(u0, t0, u1, t1):
            if substeps is not None:  # time-varying
                def matrices(uu, tt):
                    g = G(zeros, uu, tt, theta)
                    return jac(zeros, uu, tt, theta), g @ g.T

                step = time_varying_step(matrices, lambda uu, tt: f(zeros, uu, tt, theta), t0, t1 - t0, u0, u1,
                                         foh, substeps)
                return step.transition, step.offset, _psd_sqrt(step.noise_covariance)
            g = G(zeros, u0, t0, theta)
            d = discretize(jac(zeros, u0, t0, theta), g @ g.T, t1 - t0)
            b0, b1 = f(zeros, u0, t0, theta), f(zeros, u1, t1, theta)
            return d.transition, d.input_gain @ b0 + foh * d.ramp_gain @ (b1 - b0), _psd_sqrt(d.noise_covariance)

        phi, shift, noise = jax.vmap(interval)(u[:-1], t[:-1], u[1:], t[1:])

        def path(x0, zs):
            def body(x, k):
                x = phi[k] @ x + shift[k] + noise[k] @ zs[k]
                return x, x

            _, xs = jax.lax.scan(body, x0, jnp.arange(zs.shape[0]))
            return jnp.concatenate([x0[None], xs], axis=0)

        return jax.vmap(path)(init, z)

    return paths
