"""Latent forces: unmeasured inputs modelled as Gaussian processes, appended to the model's states.

A latent force ``Q`` with a kernel ([`kernels`][greyid.model.kernels]) becomes the kernel's SDE states after the
model's own, started in their stationary law, and every equation's ``Q`` becomes H z (the force's value).  A
Matérn force's first state is the force itself and keeps its name (``Q``, then ``Q_d1``, ``Q_d2`` for its
derivatives); a composite kernel's states are ``Q_1``, ``Q_2``, ... and results give the force as
[`LatentForce`][greyid.model.latent.LatentForce] weights of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp

from ..errors import ModelError
from .kernels import POSITIVE, Kernel, Named, StateSpace


@dataclass(frozen=True)
class LatentForce:
    """A latent force in a compiled structure: its name and its value as ``weights`` of the states at
    ``indices``."""

    name: str
    indices: tuple[int, ...]
    weights: tuple[float, ...]

    def values(self, states: np.ndarray, cov: np.ndarray | None = None):
        """The force's mean (…,) and variance (…,) from states (…, n) and covariances (…, n, n)."""
        h = np.asarray(self.weights)
        index = np.asarray(self.indices)
        mean = np.asarray(states)[..., index] @ h
        if cov is None:
            return mean, None
        block = np.asarray(cov)[..., index[:, None], index[None, :]]
        return mean, np.einsum("i,...ij,j->...", h, block, h)


@dataclass(frozen=True)
class Augmented:
    """The model's equations with its latent forces' states appended."""

    states: list
    noise_names: list
    drift: list
    diffusion: list
    others: list
    latent_covariance: sp.Matrix | None  # P∞ of all the forces' states (block diagonal), None without forces
    start: int
    forces: tuple[LatentForce, ...]


def state_names(name: str, kernel: Kernel, size: int) -> list[str]:
    """A Matérn force's states are the force and its derivatives; a composite kernel's are numbered."""
    if isinstance(kernel, Named) and kernel.kind.startswith("matern"):
        return [name] + [f"{name}_d{i}" for i in range(1, size)]
    return [f"{name}_{i}" for i in range(1, size + 1)]


def check_hyperparameter(force: str, role: str, value, parameters: dict) -> None:
    """A lengthscale, period or smoothness that may be zero or negative is refused by name."""
    if role not in POSITIVE:
        return
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if not value > 0:
            raise ModelError(f"latent force '{force}': its {role} must be positive, got {value}")
        return
    if isinstance(value, str) and value.strip().isidentifier():
        declared = parameters.get(value.strip())
        if declared is not None and declared.fixed and declared.init is not None:
            if not declared.init > 0:
                raise ModelError(f"latent force '{force}': its {role} '{value.strip()}' is fixed at {declared.init}; "
                                 "it must be positive")
            return
        lower = None if declared is None else declared.lower
        if lower is None or lower <= 0:
            raise ModelError(f"latent force '{force}': its {role} '{value.strip()}' may be zero or negative; give "
                             f"it a lower bound above 0 (set_parameter('{value.strip()}', lower=...)) or write it "
                             f"as a positive expression such as exp(log_{value.strip()})")


def augment(model, states: list, noise_names: list, drift: list, diffusion: list, others: list) -> Augmented:
    """Append the latent forces' states, their drift F z and noise G dω, and put each force's H z for its name
    in the model's expressions (``drift``, ``diffusion`` rows, and each list of ``others``)."""
    forces = model._latent_forces
    if not forces:
        return Augmented(states, noise_names, drift, diffusion, others, None, len(states), ())
    taken = set(states) | set(model._inputs)
    used = set().union(*(e.free_symbols for e in [*drift, *[g for row in diffusion for g in row],
                                                  *[e for part in others for e in part]]))
    start = len(states)
    states, noise_names = list(states), list(noise_names)
    drift = list(drift)
    diffusion = [list(row) for row in diffusion]
    blocks, records, replace = [], [], {}
    for name, kernel in forces.items():
        if name in taken:
            raise ModelError(f"latent force '{name}' has the name of a state or input of the model")
        symbol = sp.Symbol(name, real=True)
        if symbol not in used:
            raise ModelError(f"latent force '{name}' is used in no equation: write it where it acts, e.g. "
                             f"'+ {name}/C' in a system equation (or 'y = {name}' for a force observed alone)")
        for role, value in kernel.hyperparameters():
            check_hyperparameter(name, role, value, model._parameters)

        def value(role, given, name=name):
            return model._expression(given, f"the {role} of latent force '{name}'")

        space: StateSpace = kernel.state_space(value)
        names = state_names(name, kernel, space.size)
        clash = [n for n in names if n in taken or n in states]
        if clash:
            raise ModelError(f"latent force '{name}' needs the state name '{clash[0]}', which the model already uses")
        z = sp.Matrix([sp.Symbol(n, real=True) for n in names])
        noises = [f"dw_{name}_{j + 1}" for j in range(space.G.shape[1])]
        first = len(states)
        for i in range(space.size):
            drift.append((space.F[i, :] * z)[0])
        for row in diffusion:
            row.extend([sp.Integer(0)] * len(noises))
        for i in range(space.size):
            diffusion.append([sp.Integer(0)] * len(noise_names) + [space.G[i, j] for j in range(len(noises))])
        states += names
        noise_names += noises
        blocks.append(space.P)
        weights = [float(w) for w in space.H]
        kept = [(first + i, w) for i, w in enumerate(weights) if w != 0]
        records.append(LatentForce(name, tuple(i for i, _ in kept), tuple(w for _, w in kept)))
        replace[symbol] = (space.H * z)[0]
    for i in range(start):
        drift[i] = drift[i].xreplace(replace)
        diffusion[i] = [g.xreplace(replace) for g in diffusion[i]]
    others = [[e.xreplace(replace) for e in part] for part in others]
    return Augmented(states, noise_names, drift, diffusion, others, sp.diag(*blocks), start, tuple(records))
