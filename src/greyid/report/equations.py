"""The model's equations as MathML (rendered by the browser, no script or font needed)."""

from __future__ import annotations

import html

import sympy as sp
from sympy.printing.mathml import MathMLPresentationPrinter


class _Printer(MathMLPresentationPrinter):
    """SymPy's presentation MathML, with exp(x) written as exp(x) (as the model was written, and
    readable where x is long) instead of a raised e."""

    def _print_exp(self, expr):
        return self._print_Function(expr)


def _math(expr: sp.Expr) -> str:
    """``expr`` as MathML, with a true minus sign (U+2212) where SymPy writes a hyphen."""
    return _Printer({"mul_symbol": "dot"}).doprint(expr).replace("<mo>-</mo>", "<mo>&#8722;</mo>")


def _differential(name: str) -> str:
    return f"<mi>d</mi><mi>{html.escape(name)}</mi>"


def _block(body: str) -> str:
    return f'<math display="block"><mrow>{body}</mrow></math>'


def system_equation(state: str, drift: sp.Expr, diffusion: dict[str, sp.Expr]) -> str:
    """dx = f dt + Σ_j g_j dω_j (4.1) as a MathML block."""
    parts = [f"<mo>(</mo>{_math(drift)}<mo>)</mo><mspace width='0.2em'/><mi>dt</mi>"]
    for noise, g in diffusion.items():
        if g != 0:
            index = noise[2:] if noise.startswith("dw") else noise
            parts.append(f"<mo>(</mo>{_math(g)}<mo>)</mo><mspace width='0.2em'/>"
                         f"<mi>d</mi><msub><mi>&#969;</mi><mn>{html.escape(index)}</mn></msub>")
    return _block(_differential(state) + "<mo>=</mo>" + "<mo>+</mo>".join(parts))


def named_equation(name: str, expr: sp.Expr, noise: str | None = None) -> str:
    """``name = expr`` (observation or algebraic), with ``+ e`` for measurement noise."""
    body = f"<mi>{html.escape(name)}</mi><mo>=</mo>{_math(expr)}"
    if noise is not None:
        body += f"<mo>+</mo><msub><mi>e</mi><mi>{html.escape(noise)}</mi></msub>"
    return _block(body)


def variance_equation(name: str, expr: sp.Expr) -> str:
    body = (f"<mi>Var</mi><mo>(</mo><msub><mi>e</mi><mi>{html.escape(name)}</mi></msub><mo>)</mo>"
            f"<mo>=</mo>{_math(expr)}")
    return _block(body)


def model_equations(model) -> list[tuple[str, str]]:
    """(MathML, plain text) for each equation of a model written as equations."""
    out = []
    for a in model._algebraics:
        out.append((named_equation(a.lhs, a.rhs), a.text))
    for e in model._system:
        out.append((system_equation(e.state, e.drift, e.diffusion), e.text))
    for eq, variance, given in model._observations:
        law = model._distributions.get(eq.lhs)
        if law is None or law.gaussian:
            out.append((named_equation(eq.lhs, eq.rhs, noise=eq.lhs), eq.text))
            out.append((variance_equation(eq.lhs, variance), f"Var(e_{eq.lhs}) = {given}"))
            continue
        location = f"<msub><mi>m</mi><mi>{html.escape(eq.lhs)}</mi></msub>"
        out.append((_block(f"{location}<mo>=</mo>{_math(eq.rhs)}"), f"m_{eq.text}"))
        shape = "" if law.shape_name is None else f", {law.shape_name} = {law.shape}"
        scale = "" if given is None else f", variance {given}"
        out.append((_block(f"<mi>{html.escape(eq.lhs)}</mi><mo>~</mo><mtext>{html.escape(law.family)}</mtext><mo>(</mo>"
                           f"{location}<mtext>{html.escape(scale + shape)}</mtext><mo>)</mo>"),
                    f"{eq.lhs} ~ {law.family}(m_{eq.lhs}{scale}{shape})"))
    return out


def inline_formula(text: str, names) -> str:
    """A formula written in Python's syntax (``Ri*Ro**2``) as inline MathML (Ri·Ro²), its names as symbols."""
    expr = sp.sympify(text, locals={name: sp.Symbol(name) for name in names})
    return f"<math>{_math(expr)}</math>"
