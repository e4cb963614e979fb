"""Score and information of the Gaussian log-likelihood in natural parameters (section 3.3.2).

The score S = ∂ log L/∂θ by automatic differentiation through the filter, and
one of three estimates of the information matrix M:

* ``"fisher"``: Σ_k (∂ε_k/∂θ)ᵀR_k⁻¹(∂ε_k/∂θ) + ½ tr(R_k⁻¹ ∂R_k/∂θ_i R_k⁻¹ ∂R_k/∂θ_j),
  the expected information of the Gaussian innovations (ε_k, R_k from the
  filter, 4.32–4.33); positive semi-definite at any θ;
* ``"hessian"``: the observed information −∂² log L/∂θ∂θᵀ, which can be
  indefinite away from the optimum;
* ``"opg"``: the outer product of the per-observation scores Σ_k s_k s_kᵀ.  They
serve the Lagrange-multiplier test (5.6) and cross-validation (5.4); the
derivatives are taken with respect to the named parameters only, the others
held at their given values.
"""

from __future__ import annotations

from dataclasses import dataclass

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.jit import structure_program
from ..errors import ModelError
from ..filters.api import compiled_filter, filter_options, prepare_datasets
from .criteria import log_criterion
from .objective import (forward_hessian, forward_value_and_grad, hessian_rows, observed_innovations,
                        whitened_sensitivities)

INFORMATION_KINDS = ("fisher", "hessian", "opg")


@dataclass(frozen=True)
class Derivatives:
    """Log-likelihood, score and information at one parameter point."""

    names: tuple[str, ...]
    loglik: float
    score: np.ndarray
    information: np.ndarray
    kind: str


def _compiled(structure, options, index: tuple[int, ...]):
    key = ("derivatives", options, index)
    if key not in structure.cache:
        run = compiled_filter(structure, options, keep_outputs=False)
        idx = jnp.asarray(index, dtype=jnp.int32)

        def step_logliks(sub, base, data):
            return run(base.at[idx].set(sub), data)[0].loglik

        def total(sub, base, data):
            return log_criterion(run(base.at[idx].set(sub), data)[0])

        run_innovations = compiled_filter(structure, options, keep_outputs="innovations")

        def innovations(sub, base, data):
            innovation, innovation_cov = run_innovations(base.at[idx].set(sub), data)[1]
            return observed_innovations(innovation, innovation_cov, data.mask)

        def fisher(sub, base, data):
            (_, R), (d_eps, d_R) = innovations(sub, base, data), jax.jacfwd(innovations)(sub, base, data)
            M = whitened_sensitivities(R, jnp.moveaxis(d_eps, -1, 0), jnp.moveaxis(d_R, -1, 0))
            return M @ M.T

        hessian = hessian_rows(total, forward_hessian(options.method, len(index)))
        eye = jnp.eye(len(index))
        structure.cache[key] = tuple(
            structure_program(structure, (*key, name), lambda fun=fun: fun) for name, fun in (
                ("value_and_grad", forward_value_and_grad(total)),
                ("hessian", lambda sub, base, data: hessian(sub, eye, base, data)[2]),
                ("step_scores", jax.jacfwd(step_logliks)), ("fisher", fisher)))
    return structure.cache[key]


def loglik_derivatives(model, params, data, names, information: str = "fisher", time="t", hold="zoh",
                       method=None, time_unit=None, **options) -> Derivatives:
    """Score and information with respect to ``names`` at ``params`` (summed over data sets)."""
    if information not in INFORMATION_KINDS:
        raise ModelError(f"information must be one of {list(INFORMATION_KINDS)}, got {information!r}")
    structure = model.structure
    all_names = list(structure.parameter_names)
    unknown = [n for n in names if n not in all_names]
    if unknown:
        raise ModelError(f"'{unknown[0]}' is not a parameter of model '{model.name}'")
    theta = model.parameter_vector(params)
    prepared = prepare_datasets(structure, theta, data, time, hold, time_unit)
    opts = filter_options(structure, method, **options)
    index = tuple(all_names.index(n) for n in names)
    value_and_grad, hessian, step_scores, fisher = _compiled(structure, opts, index)
    sub = jnp.asarray(theta[list(index)])
    base = jnp.asarray(theta)
    k = len(index)
    loglik, score, info = 0.0, np.zeros(k), np.zeros((k, k))
    for _, inputs in prepared:
        value, grad = value_and_grad(sub, base, inputs)
        loglik += float(value)
        score += np.asarray(grad)
        if information == "fisher":
            info += np.asarray(fisher(sub, base, inputs))
        elif information == "hessian":
            info -= np.asarray(hessian(sub, base, inputs))
        else:
            s = np.asarray(step_scores(sub, base, inputs))
            info += s.T @ s
    return Derivatives(tuple(names), loglik, score, 0.5 * (info + info.T), information)
