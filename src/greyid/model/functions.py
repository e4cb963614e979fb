"""Models given as JAX-traceable Python functions instead of equations."""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)

import sympy as sp

from ..errors import ModelError
from .build import initial_state_expressions
from .structure import InitialCovariance, Structure, lambdify_parameters


def build_from_functions(model) -> Structure:
    """The structure of a model given by Python functions (``Model.from_functions``)."""
    import jax.numpy as jnp

    spec = model._functions
    states, params = spec["states"], spec["parameters"]
    param_syms = [sp.Symbol(p, real=True) for p in params]
    mean, rows = initial_state_expressions(model, list(states))
    used = {s.name for e in mean for s in e.free_symbols}
    if isinstance(rows, list):
        used |= {s.name for r in rows for e in r for s in e.free_symbols}
    extra = used - set(params)
    if extra:
        raise ModelError(f"initial state refers to '{sorted(extra)[0]}', which is not a declared parameter")

    def wrap(fn):
        def model_function(x, u, t, theta):
            p = {name: theta[i] for i, name in enumerate(params)}
            return jnp.asarray(fn(x, u, t, p), dtype=jnp.float64)

        return model_function

    n = len(states)
    diffuse = tuple(list(states).index(x) for x in model._diffuse)
    if diffuse and spec["kind"] == "nonlinear":
        raise ModelError(f"the diffuse initial state {list(model._diffuse)} needs a linear model (the exact diffuse "
                         "start is a Kalman filter's), but this model is declared nonlinear")
    if isinstance(rows, str):
        initial_cov = InitialCovariance(rows, scale=model._initial_scale, diffuse=diffuse,
                                        seen_by=((),) * len(diffuse))
    else:
        initial_cov = InitialCovariance("matrix", matrix=lambdify_parameters(
            [e for r in rows for e in r], param_syms, (n, n)), diffuse=diffuse,
            seen_by=((),) * len(diffuse))
    import jax

    g_shape = jax.eval_shape(wrap(spec["diffusion"]), jnp.zeros(n), jnp.zeros(len(spec["inputs"])),
                             jnp.zeros(()), jnp.ones(len(params)))
    if len(g_shape.shape) != 2 or g_shape.shape[0] != n:
        raise ModelError(f"diffusion must return an array of shape ({n}, m), got {g_shape.shape}")
    return Structure(
        state_names=tuple(states),
        input_names=tuple(spec["inputs"]),
        output_names=tuple(spec["outputs"]),
        parameter_names=tuple(params),
        noise_names=tuple(f"dw{j + 1}" for j in range(g_shape.shape[1])),
        kind=spec["kind"],
        drift=wrap(spec["drift"]),
        diffusion=wrap(spec["diffusion"]),
        observation=wrap(spec["observation"]),
        observation_variance=wrap(spec["observation_variance"]),
        initial_mean=lambdify_parameters(mean, param_syms, (n,)),
        initial_covariance=initial_cov,
    )
