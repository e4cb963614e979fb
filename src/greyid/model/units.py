"""Physical units of a model's names and the dimensional check of its equations (Pint).

With units given (``model.set_units({...})`` or a model file's ``[units]``
table, the time column's name included), every equation is checked term by
term before any fit:

* each drift term of ``dX`` has the unit of X per time unit;
* each diffusion coefficient of ``dX`` the unit of X per square root of time;
* each observation term the unit of its output, its variance the output's squared.

Units must agree in scale too: a term in kW/(J/K) where K/h is expected is
3.6·10⁶ times too large, and is reported so.  A name without a unit counts
as dimensionless, and a message that involves one says so.  A parameter used
as ``exp(p)`` (CTSM's log-parametrisation of a positive quantity) may be given
the unit of exp(p): ``"p11": "K/h^0.5"`` makes ``exp(p11)*dw1`` a diffusion in
K/√h.  Literal numbers
take the unit their place needs (an offset such as 273.15 beside a
temperature).  Units of derived quantities follow from their expressions,
except where a decimal factor converts units by hand (``Ci*3600/1e6``): those
get none.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from typing import Mapping

import sympy as sp

from ..errors import ModelError
from .delays import delay
from .symbols import TIME


@lru_cache(maxsize=1)
def registry():
    try:
        import pint
    except ImportError:
        raise ModelError('units need Pint: pip install pint (a dependency of greyid; reinstall it)') from None
    return pint.UnitRegistry()


def pretty(text: str) -> str:
    """A unit string as a reader writes it (``m^2`` → m², ``degC`` → °C); unchanged if Pint cannot read it."""
    if not text:
        return text
    if text.startswith("log(") and text.endswith(")"):  # a log-parameter's unit: log of a unit
        return f"log({pretty(text[4:-1])})"
    try:
        shown = format(registry().Unit(text), "~P") or text
    except Exception:  # Pint raises several kinds; the text as given is still right
        return text
    return re.sub(r"([^\s/·]+)⁰⋅⁵", r"√\1", shown)  # h⁰⋅⁵ → √h


def parse_units(units: Mapping[str, str]) -> dict:
    """``{name: pint.Unit}``; an unknown unit string is a named error."""
    ureg = registry()
    out = {}
    for name, text in units.items():
        if not isinstance(name, str) or not isinstance(text, str):
            raise ModelError(f"units map names to unit strings, e.g. {{'Ti': 'K'}}; got {name!r}: {text!r}")
        try:
            q = ureg.Quantity(1.0, text if text.strip() else "dimensionless")
            if not q._is_multiplicative:
                # degC and degF: equations hold their differences (and the offset cancels in
                # every linear use), so the algebra works in the matching delta unit.
                q = ureg.Quantity(1.0, f"delta_{q.units}")
        except Exception as error:  # Pint raises several kinds
            raise ModelError(f"unknown unit '{text}' for '{name}': {error}") from None
        out[name] = q
    return out


class _Any:
    """A literal number: it takes whatever unit its place needs."""


ANY = _Any()


class UnitMismatch(ModelError):
    pass


@dataclass
class Term:
    equation: str
    term: str
    unit: str
    expected: str
    ok: bool
    note: str = ""

    def line(self) -> str:
        mark = "✓" if self.ok else "✗"
        return f"in {self.equation}: term {self.term} has unit {self.unit}, expected {self.expected} {mark}{self.note}"


class UnitAlgebra:
    """Units of SymPy expressions over named quantities."""

    def __init__(self, units: Mapping[str, object], time_unit, parameters=()):
        self.ureg = registry()
        self.units = dict(units)
        self.parameters = set(parameters)
        self.time = time_unit
        self.assumed: set[str] = set()

    def of_symbol(self, symbol: sp.Symbol):
        if symbol == TIME:
            return self.time
        if symbol.name in self.units:
            return self.units[symbol.name]
        self.assumed.add(symbol.name)
        return self.ureg.Quantity(1.0, "dimensionless")

    def same(self, a, b) -> bool:
        if a is ANY or b is ANY:
            return True
        if a.dimensionality != b.dimensionality:
            return False
        return abs(float(a.to(b.units).magnitude) / float(b.magnitude) - 1.0) < 1e-9

    def dimensionless(self, q) -> bool:
        return q is ANY or self.same(q, self.ureg.Quantity(1.0, "dimensionless"))

    def of(self, expr: sp.Expr):
        """The unit of ``expr`` as a Pint quantity of magnitude 1 in its own units (ANY for numbers)."""
        if expr.is_Number or expr in (sp.pi, sp.E) or not expr.free_symbols:
            return ANY
        if isinstance(expr, sp.Symbol):
            return self.of_symbol(expr)
        if isinstance(expr, sp.Add):
            known = [(term, self.of(term)) for term in expr.args]
            known = [(term, q) for term, q in known if q is not ANY]
            if not known:
                return ANY
            first_term, first = known[0]
            for term, q in known[1:]:
                if not self.same(q, first):
                    raise UnitMismatch(f"'{term}' has unit {_show(q)} but '{first_term}' beside it has "
                                       f"{_show(first)}{self._note(expr)}")
            return first
        if isinstance(expr, sp.Mul):
            out = ANY
            for factor in expr.args:
                q = self.of(factor)
                if q is ANY:
                    continue
                out = q if out is ANY else out * q
            return out
        if isinstance(expr, sp.Pow):
            base, exponent = expr.args
            q = self.of(base)
            if exponent.is_Number:
                return ANY if q is ANY else q ** float(exponent)
            if not self.dimensionless(q) or not self.dimensionless(self.of(exponent)):
                raise UnitMismatch(f"'{expr}' raises {_show(q)} to a non-numeric power{self._note(expr)}")
            return self.ureg.Quantity(1.0, "dimensionless")
        if isinstance(expr, (sp.Abs,)):
            return self.of(expr.args[0])
        if isinstance(expr, (sp.Min, sp.Max)):
            return self.of(sp.Add(*[a - expr.args[0] for a in expr.args[1:]], expr.args[0], evaluate=False)) \
                if len(expr.args) > 1 else self.of(expr.args[0])
        if isinstance(expr, sp.Piecewise):
            return self.of(sp.Add(*[value for value, _ in expr.args], evaluate=False))
        if isinstance(expr, sp.Heaviside) or isinstance(expr, sp.sign):
            return self.ureg.Quantity(1.0, "dimensionless")
        if isinstance(expr, delay):  # the input, a delay later: its unit, with a delay in time units
            signal, tau = expr.args
            q = self.of(tau)
            if q is not ANY and not self.same(q, self.time):
                raise UnitMismatch(f"the delay '{tau}' in '{expr}' has unit {_show(q)}; it must be in the time "
                                   f"unit {_show(self.time)}{self._note(tau)}")
            return self.of(signal)
        argument = expr.args[0] if isinstance(expr, sp.exp) else None
        if isinstance(argument, sp.Symbol) and argument.name in self.units and argument.name in self.parameters:
            # The log-parametrisation of CTSM (exp(p11) for a noise intensity): p holds the
            # logarithm of a quantity in the unit given to p, so exp(p) has that unit.
            return self.units[expr.args[0].name]
        if isinstance(expr, sp.Function):
            for argument in expr.args:
                q = self.of(argument)
                if not self.dimensionless(q):
                    raise UnitMismatch(f"the argument '{argument}' of {expr.func.__name__} has unit {_show(q)}; "
                                       f"it must be dimensionless{self._note(argument)}")
            return self.ureg.Quantity(1.0, "dimensionless")
        if isinstance(expr, (sp.logic.boolalg.Boolean, sp.core.relational.Relational)):
            return ANY
        raise ModelError(f"cannot work out the unit of '{expr}'")

    def _note(self, expr) -> str:
        names = sorted(s.name for s in expr.free_symbols if s.name in self.assumed)
        return f" ({', '.join(names)} ha{'s' if len(names) == 1 else 've'} no unit: taken as dimensionless)" \
            if names else ""


def _show(q) -> str:
    if q is ANY:
        return "(any)"
    magnitude = float(q.magnitude)
    unit = f"{q.units:~P}" or "1"
    return unit if abs(magnitude - 1.0) < 1e-12 else f"{magnitude:.6g} {unit}"


def _describe(algebra, q, expected) -> str:
    """``unit = simplified`` as in "kW/(kWh/K) = K/h"."""
    if q is ANY:
        return "(a number)"
    shown = _show(q)
    if q.dimensionality == expected.dimensionality:
        converted = q.to(expected.units)
        other = _show(converted)
        if other != shown:
            return f"{shown} = {other}"
    return shown


def check_terms(algebra: UnitAlgebra, label: str, expr: sp.Expr, expected) -> list[Term]:
    """One [`Term`][greyid.model.units.Term] per additive term of ``expr`` against the ``expected`` unit."""
    terms = sp.Add.make_args(expr)
    out = []
    for term in terms:
        try:
            q = algebra.of(term)
        except UnitMismatch as error:
            out.append(Term(label, str(term), "inconsistent", _show(expected), False, f": {error}"))
            continue
        ok = q is ANY or algebra.same(q, expected)
        note = ""
        if not ok and q is not ANY and q.dimensionality == expected.dimensionality:
            factor = float(q.to(expected.units).magnitude) / float(expected.magnitude)
            note = f" (a factor {factor:.6g} apart: units of different scale)"
        if not ok:
            note += algebra._note(term)
        out.append(Term(label, str(term), _describe(algebra, q, expected), _show(expected), ok, note))
    return out


def check_model_units(model, units: Mapping[str, str], time_name: str = "t") -> list[Term]:
    """Every term of ``model``'s equations checked against the units; see the module doc."""
    parsed = parse_units(units)
    if time_name not in parsed and "t" not in parsed:
        raise ModelError(f"units are given but not the unit of the time column '{time_name}' "
                         f"(e.g. '{time_name}': 'h')")
    time_unit = parsed.get(time_name, parsed.get("t"))
    forces = getattr(model, "_latent_forces", {})
    names = (set(model.state_names) | set(model.input_names) | set(model.output_names) | set(model.parameter_names)
             | set(forces))
    unknown = sorted(set(parsed) - names - {time_name, "t"})
    if unknown:
        raise ModelError(f"units given for '{unknown[0]}', which is not a name of model '{model.name}'")
    algebra = UnitAlgebra({n: q for n, q in parsed.items() if n not in (time_name, "t")}, time_unit,
                          model.parameter_names)
    dimensionless = algebra.ureg.Quantity(1.0, "dimensionless")
    unit = {n: parsed.get(n, dimensionless) for n in names}
    sub = model._substitute_algebraics
    terms = []
    for equation in model._system:
        x = equation.state
        terms += check_terms(algebra, f"d{x} (drift)", sub(equation.drift), unit[x] / time_unit)
        for wiener, coefficient in equation.diffusion.items():
            terms += check_terms(algebra, f"d{x} ({wiener})", sub(coefficient), unit[x] / time_unit ** 0.5)
    for eq, variance, _ in model._observations:
        law = model._distributions.get(eq.lhs)
        family = "normal" if law is None else law.family
        # A probability (binomial) is dimensionless, a count's mean has the count's unit.
        terms += check_terms(algebra, eq.lhs, sub(eq.rhs), dimensionless if family == "binomial" else unit[eq.lhs])
        if family in ("normal", "student_t"):
            terms += check_terms(algebra, f"variance of {eq.lhs}", sub(variance), unit[eq.lhs] ** 2)
        elif family == "lognormal":  # the variance of log y
            terms += check_terms(algebra, f"variance of {eq.lhs}", sub(variance), dimensionless)
        if law is not None and law.shape_name is not None:
            shape = model._expression(law.shape, f"{law.shape_name} of {eq.lhs}")
            terms += check_terms(algebra, f"{law.shape_name} of {eq.lhs}", sub(shape), dimensionless)
    # A force's scale is a standard deviation in its unit, its lengthscale and period are times.
    expected = {"scale": None, "lengthscale": time_unit, "period": time_unit, "smoothness": dimensionless}
    for name, kernel in forces.items():
        for role, value in kernel.hyperparameters():
            want = unit[name] if role == "scale" else expected[role]
            terms += check_terms(algebra, f"{role} of latent force {name}",
                                 sub(model._expression(value, f"{role} of latent force '{name}'")), want)
    return terms


def derived_unit(model, units: Mapping[str, str], expression: str, time_name: str = "t") -> str:
    """The unit of a derived quantity's expression, in the model's units ("" if it has none)."""
    from .equations import parse_expression

    parsed = parse_units(units)
    algebra = UnitAlgebra({n: q for n, q in parsed.items() if n not in (time_name, "t")},
                          parsed.get(time_name, parsed.get("t")), model.parameter_names)
    expr = model._substitute_algebraics(parse_expression(expression, "derived quantity"))
    if any(isinstance(a, sp.Float) for a in sp.preorder_traversal(expr)):
        return ""  # a decimal factor is a unit conversion written by hand: the unit is the user's to say
    try:
        q = algebra.of(expr)
    except UnitMismatch as error:
        raise ModelError(f"the derived quantity '{expression}' mixes units: {error}") from None
    return "" if q is ANY else _show(q)


#: "time in seconds", "time is in hours", "time [h]": how model descriptions say their time unit.
_DESCRIBED_TIME = re.compile(r"\btime(?: is)?(?: measured)? in (seconds?|minutes?|hours?|days?)\b"
                             r"|\btime \[(s|min|h|d)\]", re.IGNORECASE)
_TIME_WORDS = {"second": "s", "minute": "min", "hour": "h", "day": "d"}


def time_unit(model, time_name: str = "t", settings: Mapping | None = None) -> str | None:
    """The unit of the model's time for axis labels: ``[units]`` of the time column or of t, else the
    ``time_unit`` timestamps were read in, else what the model's description says ("time in seconds");
    None where nothing says it."""
    units = model.units
    for key in (time_name, "t"):
        if units.get(key):
            return units[key]
    if settings and settings.get("time_unit"):
        return str(settings["time_unit"])
    found = _DESCRIBED_TIME.search(getattr(model, "description", "") or "")
    if found is None:
        return None
    word = found.group(1)
    return _TIME_WORDS[word.lower().rstrip("s")] if word else found.group(2)


def figure_units(model, time_name: str = "t", settings: Mapping | None = None) -> dict:
    """The model's units for figures, with the time column's unit ([`time_unit()`][greyid.model.units.time_unit]) where
    it has one."""
    units = model.units
    unit = time_unit(model, time_name, settings)
    if unit and not units.get(time_name):
        units[time_name] = unit
    return units
