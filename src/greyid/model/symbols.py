"""Symbols with a fixed meaning in every equation: time and its increment."""

import sympy as sp

#: The time t of the equations (and of ``delay(u, tau)``'s shifted inputs).
TIME = sp.Symbol("t", real=True)
#: The increment dt of ``dx = f dt + G dω``.
DT = sp.Symbol("dt", real=True)
