"""Delayed inputs: ``delay(u, tau)`` in an equation is input ``u`` at time t − tau.

Chapter 8's fuel film model has φ(t + Δt) = k_b ṁ_f(t): the injected fuel acts
on the film a transport delay later.  In equations the delay is written
``delay(mf, tau)``, with ``tau`` a number or an expression of parameters (an
estimable delay), in the data's time unit.  Each distinct ``delay(u, tau)``
becomes one extra input of the compiled model functions, which the filters fill
in with the delayed input's values (see [`greyid.filters.delays`][greyid.filters.delays]).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import sympy as sp

from ..errors import ModelError
from .symbols import TIME


class delay(sp.Function):  # noqa: N801  (the name users write)
    """``delay(u, tau)``: input u at time t − tau (kept unevaluated by SymPy)."""

    nargs = 2


@dataclass(frozen=True)
class DelayedInput:
    """One ``delay(u, tau)`` of a model: the input it delays and its delay as a function of θ."""

    name: str  # as written, e.g. "delay(mf, tau)"
    input: int  # index of the delayed input among the model's inputs
    expression: sp.Expr  # tau in the parameters
    tau: Callable | None = None  # theta -> tau, set once the parameters are ordered


def find_delays(exprs, inputs: list[str], states: list[str]) -> list[tuple[sp.Expr, DelayedInput, sp.Symbol]]:
    """Every distinct ``delay(u, tau)`` in ``exprs``: ``[(call, DelayedInput, stand-in symbol)]``.

    The stand-in symbol replaces the call in the model functions (an extra input).
    """
    calls = []
    for expr in exprs:
        for call in sp.preorder_traversal(expr):
            if isinstance(call, delay) and call not in calls:
                calls.append(call)
    found = []
    for call in calls:
        signal, tau = call.args
        if not (isinstance(signal, sp.Symbol) and signal.name in inputs):
            raise ModelError(f"'{call}': the first argument of delay() must be an input of the model "
                             f"(inputs: {inputs})")
        bad = sorted(s.name for s in tau.free_symbols if s.name in inputs or s.name in states or s == TIME)
        if bad:
            raise ModelError(f"'{call}': the delay may depend on parameters only, not on '{bad[0]}'")
        if any(isinstance(a, delay) for a in sp.preorder_traversal(tau)):
            raise ModelError(f"'{call}': a delay cannot contain another delay()")
        if tau.is_number and float(tau) < 0:
            raise ModelError(f"'{call}': the delay {float(tau)} is negative; a delay looks back in time (tau ≥ 0)")
        stand_in = sp.Symbol(f"{signal.name}@delay{len(found)}", real=True)
        found.append((call, DelayedInput(str(call), inputs.index(signal.name), tau), stand_in))
    return found


def delay_parameters(structure) -> dict[str, str]:
    """``{parameter: "delay(u, tau)"}`` for each delay that is a parameter itself (estimable as it stands)."""
    return {d.expression.name: d.name for d in structure.delays if d.expression.is_Symbol}
