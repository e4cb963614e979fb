"""Parsing of model equations written as text into SymPy expressions.

The syntax is that of CTSM: ``dTi = (Te - Ti)/(Ri*Ci)*dt + exp(p11)*dw1`` for a
state equation, ``yTi = Ti`` for an observation and ``theta = exp(logtheta)`` for
an algebraic definition.  ``dt`` is the time differential, every name starting
with ``dw`` is a Wiener increment, ``t`` is time, and every other name that is not
a state, an input or a known function is a parameter.
"""

from __future__ import annotations

import io
import keyword
import re
import tokenize
from dataclasses import dataclass

import sympy as sp
from sympy.parsing.sympy_parser import convert_xor, parse_expr, standard_transformations

from ..errors import ModelError
from .delays import delay
from .symbols import DT
from .physics import glazing_transmittance_expression

#: Functions allowed in equations, by the name a user writes.
FUNCTIONS: dict[str, object] = {
    "exp": sp.exp,
    "log": sp.log,
    "ln": sp.log,
    "sqrt": sp.sqrt,
    "sin": sp.sin,
    "cos": sp.cos,
    "tan": sp.tan,
    "asin": sp.asin,
    "acos": sp.acos,
    "atan": sp.atan,
    "atan2": sp.atan2,
    "sinh": sp.sinh,
    "cosh": sp.cosh,
    "tanh": sp.tanh,
    "abs": sp.Abs,
    "Abs": sp.Abs,
    "sign": sp.sign,
    "min": sp.Min,
    "Min": sp.Min,
    "max": sp.Max,
    "Max": sp.Max,
    "Piecewise": sp.Piecewise,
    "piecewise": sp.Piecewise,
    "Heaviside": sp.Heaviside,
    "erf": sp.erf,
    "pow": sp.Pow,
    "invlogit": lambda z: 1 / (1 + sp.exp(-z)),
    "logit": lambda z: sp.log(z / (1 - z)),
    "glazing_transmittance": glazing_transmittance_expression,
    "delay": delay,
}

_CONSTANTS = {"pi": sp.pi, "True": sp.true, "False": sp.false}
#: Names that an equation reads as a constant, not as a parameter: what each means.
CONSTANTS = {"pi": "π = 3.14159…", "True": "true", "False": "false"}
_EQUALS = re.compile(r"(?<![<>=!])=(?!=)")


def is_wiener_name(name: str) -> bool:
    """True for names of Wiener increments (``dw``, ``dw1``, ``dw_i`` ...)."""
    return name.startswith("dw")


@dataclass(frozen=True)
class Equation:
    """A parsed equation ``lhs = rhs`` together with the text it came from."""

    lhs: str
    rhs: sp.Expr
    text: str


def _names_in(text: str, where: str) -> tuple[set[str], set[str]]:
    """Split the names of an expression into plain names and called functions."""
    names: set[str] = set()
    called: set[str] = set()
    try:
        tokens = list(tokenize.generate_tokens(io.StringIO(text).readline))
    except (tokenize.TokenError, IndentationError, SyntaxError) as err:
        raise ModelError(f"cannot parse {where} '{text}': {err}") from None
    for i, tok in enumerate(tokens):
        if tok.type != tokenize.NAME:
            continue
        nxt = tokens[i + 1] if i + 1 < len(tokens) else None
        if nxt is not None and nxt.type == tokenize.OP and nxt.string == "(":
            called.add(tok.string)
        else:
            names.add(tok.string)
    return names, called


def parse_expression(text: str, where: str = "expression") -> sp.Expr:
    """Parse one expression; ``where`` names it in error messages."""
    if not isinstance(text, str) or not text.strip():
        raise ModelError(f"{where} is empty")
    names, called = _names_in(text, where)
    unknown = sorted(called - set(FUNCTIONS))
    if unknown:
        raise ModelError(
            f"unknown function '{unknown[0]}' in {where} '{text}'; "
            f"known functions: {', '.join(sorted(FUNCTIONS))}"
        )
    reserved = sorted(n for n in names if keyword.iskeyword(n) and n not in _CONSTANTS)
    if reserved:
        raise ModelError(f"'{reserved[0]}' is a reserved word and cannot be a name in {where} '{text}'")
    local = {name: sp.Symbol(name, real=True) for name in names}
    local.update({n: v for n, v in _CONSTANTS.items() if n in names})
    local.update({n: FUNCTIONS[n] for n in called})
    try:
        expr = parse_expr(text, local_dict=local, transformations=standard_transformations + (convert_xor,))
    except Exception as err:  # SymPy raises many kinds of errors for bad syntax
        raise ModelError(f"cannot parse {where} '{text}': {err}") from None
    if isinstance(expr, (int, float)):
        expr = sp.Float(expr)
    if not isinstance(expr, sp.Expr):
        raise ModelError(f"{where} '{text}' is not an arithmetic expression")
    if expr.has(sp.zoo, sp.nan, sp.oo, -sp.oo):
        raise ModelError(f"{where} '{text}' divides by zero or is infinite (a term such as 1/0)")
    if expr.has(sp.I):
        raise ModelError(f"{where} '{text}' is complex-valued (the square root or logarithm of a negative "
                         "number?); equations must be real")
    return expr


def split_equation(text: str, where: str) -> tuple[str, str]:
    """Split ``lhs = rhs`` at its single assignment sign."""
    if not isinstance(text, str):
        raise ModelError(f"{where} must be text, got {type(text).__name__}")
    parts = _EQUALS.split(text)
    if len(parts) != 2:
        raise ModelError(f"{where} '{text}' must have the form 'lhs = rhs' with a single '='")
    lhs, rhs = parts[0].strip(), parts[1].strip()
    if not lhs.isidentifier():
        raise ModelError(f"the left-hand side '{lhs}' of {where} '{text}' must be a single name")
    if not rhs:
        raise ModelError(f"{where} '{text}' has an empty right-hand side")
    return lhs, rhs


def parse_equation(text: str, where: str) -> Equation:
    """Parse ``lhs = rhs`` into the left name and the right expression."""
    lhs, rhs = split_equation(text, where)
    return Equation(lhs=lhs, rhs=parse_expression(rhs, f"{where} '{text}'"), text=text)


@dataclass(frozen=True)
class SystemEquation:
    """``d<state> = drift*dt + sum_j diffusion_j * dw_j`` split into its parts."""

    state: str
    drift: sp.Expr
    diffusion: dict[str, sp.Expr]
    text: str


def parse_system_equation(text: str) -> SystemEquation:
    """Split a state equation into drift and diffusion terms (model (4.1))."""
    where = "system equation"
    lhs, rhs_text = split_equation(text, where)
    if not lhs.startswith("d") or len(lhs) < 2:
        raise ModelError(f"the left-hand side of system equation '{text}' must be 'd<state>', e.g. 'dTi'")
    state = lhs[1:]
    if state == "t" or is_wiener_name(lhs):
        raise ModelError(f"'{state}' cannot be a state name in system equation '{text}'")
    rhs = parse_expression(rhs_text, f"system equation '{text}'")
    wieners = sorted((s for s in rhs.free_symbols if is_wiener_name(s.name)), key=lambda s: s.name)
    differentials = [DT, *wieners]
    # '0*dt' (a state without drift) is 0 to SymPy: the text still says dt.
    if DT not in rhs.free_symbols and DT.name not in _names_in(rhs_text, where)[0]:
        raise ModelError(f"system equation '{text}' has no '*dt' term (write '0*dt' for a state without drift)")
    rest = rhs.subs({d: 0 for d in differentials})
    if sp.simplify(rest) != 0:
        raise ModelError(
            f"system equation '{text}' has a term without dt or dw: '{rest}'; "
            "every term must be multiplied by dt or by a Wiener increment dw"
        )
    drift = sp.diff(rhs, DT)
    diffusion = {w.name: sp.diff(rhs, w) for w in wieners}
    for part in [drift, *diffusion.values()]:
        if part.free_symbols & set(differentials):
            raise ModelError(f"system equation '{text}' is not linear in dt and the dw terms")
    return SystemEquation(state=state, drift=drift, diffusion=diffusion, text=text)
