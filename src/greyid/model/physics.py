"""Physical functions usable in model equations, as SymPy expressions (so they differentiate exactly).

* ``glazing_transmittance(theta, N)`` — the direct transmittance of N glass
  covers at incidence angle θ (radians), reflection losses only: F(θ_inc, α_eff)
  of (7.52) and figure 7.14, N any positive real (the effective number of panes).
"""

from __future__ import annotations

import numpy as np
import sympy as sp

#: Refractive index of window glass (Duffie & Beckman, Solar engineering of thermal processes, 5.1).
GLASS_INDEX = 1.526


def glazing_transmittance_expression(theta, panes, index=GLASS_INDEX):
    """τ(θ, N): transmittance of N glass covers for beam radiation at incidence θ (radians),
    reflection losses only (Fresnel, Duffie & Beckman (5.1.4)); the theoretical F(θ_inc, α_eff)
    of (7.52) and figure 7.14, with N any positive real (the effective number of panes α_eff).

    r_⊥ = ((cos θ − n cos θ₂)/(cos θ + n cos θ₂))², r_∥ = ((n cos θ − cos θ₂)/(n cos θ + cos θ₂))²,
    sin θ₂ = sin θ / n, τ = ½ Σ (1 − r)/(1 + (2N − 1) r).  Smooth at normal
    incidence; 0 from 90° on (the sun behind the glazing).
    """
    c1 = sp.Max(sp.cos(theta), 0)
    c2 = sp.sqrt(1 - (1 - c1 ** 2) / index ** 2)
    perpendicular = ((c1 - index * c2) / (c1 + index * c2)) ** 2
    parallel = ((index * c1 - c2) / (index * c1 + c2)) ** 2
    return sp.Rational(1, 2) * sum((1 - r) / (1 + (2 * panes - 1) * r) for r in (perpendicular, parallel))


def glazing_transmittance(theta, panes, index: float = GLASS_INDEX):
    """NumPy values of [`glazing_transmittance_expression()`][greyid.model.physics.glazing_transmittance_expression] (θ
    in radians)."""
    theta = np.asarray(theta, dtype=np.float64)
    c1 = np.clip(np.cos(theta), 0.0, None)
    c2 = np.sqrt(1 - (1 - c1 ** 2) / index ** 2)
    perpendicular = ((c1 - index * c2) / (c1 + index * c2)) ** 2
    parallel = ((index * c1 - c2) / (index * c1 + c2)) ** 2
    return 0.5 * sum((1 - r) / (1 + (2 * np.asarray(panes) - 1) * r) for r in (perpendicular, parallel))
