"""Parameter declarations: initial values, bounds and fixed values."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ModelError


@dataclass(frozen=True)
class Parameter:
    """One model parameter as the user declared it.

    ``init`` is the starting value for estimation, or the value itself when
    ``fixed`` is true.  Bounds are optional (``None`` means unbounded).
    ``prior`` is an optional Gaussian prior ``(mean, sd)`` used by MAP
    estimation (3.46).
    """

    name: str
    init: float | None = None
    lower: float | None = None
    upper: float | None = None
    fixed: bool = False
    prior: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.fixed, (bool, np.bool_)):
            raise ModelError(f"parameter '{self.name}': fixed must be True or False, got {self.fixed!r}")
        # An infinite bound is no bound (TOML's -inf, NumPy's inf).
        for label in ("lower", "upper"):
            value = getattr(self, label)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isinf(value):
                if (label == "lower") == (value < 0):
                    object.__setattr__(self, label, None)
                else:
                    raise ModelError(f"parameter '{self.name}': {label} bound {value} leaves no room for a value")
        if self.prior is not None:
            prior = self.prior
            if not (isinstance(prior, (tuple, list)) and len(prior) == 2
                    and all(isinstance(v, (int, float)) and math.isfinite(v) for v in prior) and prior[1] > 0):
                raise ModelError(f"parameter '{self.name}': prior must be (mean, sd) with sd > 0, got {prior!r}")
            object.__setattr__(self, "prior", (float(prior[0]), float(prior[1])))
        for label, value in (("init", self.init), ("lower", self.lower), ("upper", self.upper)):
            if value is not None and (not isinstance(value, (int, float)) or math.isnan(value)):
                raise ModelError(f"parameter '{self.name}': {label} must be a number, got {value!r}")
        if self.lower is not None and self.upper is not None and self.lower >= self.upper:
            raise ModelError(
                f"parameter '{self.name}': lower bound {self.lower} must be below upper bound {self.upper}"
            )
        if self.init is not None and not math.isfinite(self.init):
            raise ModelError(f"parameter '{self.name}': init must be finite, got {self.init}")
        if self.init is not None and not self.fixed:
            if (self.lower is not None and self.init < self.lower) or (
                self.upper is not None and self.init > self.upper
            ):
                raise ModelError(
                    f"parameter '{self.name}': initial value {self.init} is outside its bounds "
                    f"[{self.lower}, {self.upper}]"
                )
        if self.fixed and self.init is None:
            raise ModelError(f"parameter '{self.name}' is fixed but has no value")


def equation_expressions(structure) -> list:
    """Every expression of the model's equations (drift, diffusion, observation, variances, covariances
    and the delays' expressions), as SymPy expressions."""
    expressions = [e for key in ("drift", "diffusion", "observation", "variance", "covariance")
                   for e in structure.equations[key]]
    return expressions + [d.expression for d in structure.delays if hasattr(d.expression, "free_symbols")]


def in_dynamics(structure, names) -> list[str]:
    """The parameters of ``names`` that enter the equations, not only the initial state: those a
    stationary experiment (the information per sample, G, H and Σ) can see."""
    used = {s.name for e in equation_expressions(structure) for s in e.free_symbols}
    return [n for n in names if n in used]


def log_parametrised(structure) -> set[str]:
    """Parameters that enter the equations only as exp(p) (CTSM's log-parametrisation of noise
    intensities: p11 in exp(p11)·dω): p is the logarithm of a quantity, 0 is not a null value."""
    import sympy as sp

    out = set()
    expressions = equation_expressions(structure)
    for name in structure.parameter_names:
        symbol = sp.Symbol(name, real=True)
        occurs = [e for e in expressions if any(s.name == name for s in e.free_symbols)]
        if not occurs:
            continue
        symbol = next(s for e in occurs for s in e.free_symbols if s.name == name)
        dummy = sp.Dummy()
        # Every occurrence inside exp(p): replacing exp(p) by a dummy removes p altogether.
        if all(symbol not in e.replace(lambda x, symbol=symbol: isinstance(x, sp.exp) and x.args[0] == symbol,
                                       lambda x, dummy=dummy: dummy).free_symbols for e in occurs):
            out.add(name)
    return out


def tests_against_zero(model) -> dict[str, bool]:
    """Whether a t-test of each parameter against 0 means anything: not for a log-parameter (0 is
    a value of 1 in its unit) nor for a parameter of the initial state only (an initial temperature
    of 0 °C is no null hypothesis)."""
    structure = model.structure
    names = list(structure.parameter_names)
    dynamic = set(in_dynamics(structure, names))
    logs = log_parametrised(structure)
    return {name: name in dynamic and name not in logs for name in names}
