"""Where the optimiser starts: the initial values, a nested model's fit, a space-filling design.

* ``init_from=fit_of_a_smaller_model``: the parameters both models share start at
  the smaller model's estimates, and the new ones where the larger model
  reduces to the smaller (a sensor with a vanishing time constant, a resistance
  large enough to decouple a state).  Where that limit lies is the model's own
  knowledge: [`Model.set_nested_start()`][greyid.api.Model.set_nested_start] (the library's RC models declare
  theirs); without it the new parameters take their declared initial values.
* ``starts=k``: k − 1 further points by a Latin hypercube (SciPy's ``qmc``,
  seeded) in the coordinates the optimiser works in: the middle 96 % of a
  two-sided bound's logit, a factor e^±1.5 around the initial value for a
  one-sided bound, and ± max(|θ₀|, 1) for an unbounded parameter.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..errors import ModelError
from .transforms import BOTH, LOWER, NONE, UPPER, Transform

#: Half-width of the range of z a space-filling start is drawn from, by kind of bound.
LOGIT_RANGE = float(np.log(0.98 / 0.02))
LOG_RANGE = 1.5


def space_filling(transform: Transform, z0: np.ndarray, count: int, seed: int) -> list[np.ndarray]:
    """``count`` points of a Latin hypercube in z around ``z0`` (see the module doc)."""
    if count <= 0:
        return []
    from scipy.stats import qmc  # here: scipy.stats is slow to import, and one start needs none

    unit = qmc.LatinHypercube(d=len(z0), seed=seed).random(count)  # in [0, 1)
    spread = 2.0 * unit - 1.0
    theta0 = transform.to_theta(z0, np)
    points = []
    for row in spread:
        z = np.array(z0, dtype=np.float64)
        for i, kind in enumerate(transform.kind):
            if kind == BOTH:
                z[i] = LOGIT_RANGE * row[i]
            elif kind in (LOWER, UPPER):
                z[i] = z0[i] + LOG_RANGE * row[i]
            else:
                z[i] = theta0[i] + row[i] * max(abs(theta0[i]), 1.0)
        points.append(z)
    return points


def nested_start(model, other, names, free, lower, upper) -> dict[str, float]:
    """Initial values of ``model``'s free parameters from ``other``, the fit of a model it extends.

    Shared parameters take the other fit's estimates (moved just inside the
    bounds if they sit on one); the model's nested-start rule, if any, sets the
    rest; the remaining ones keep their declared initial values.
    """
    values = other if isinstance(other, Mapping) else getattr(other, "values", other)
    if not isinstance(values, Mapping):
        raise ModelError("init_from takes a FitResult (or a mapping of parameter values)")
    start = {}
    rule = getattr(model, "nested_start", None)
    if rule is not None:
        start.update({k: float(v) for k, v in rule(dict(values)).items() if k in names})
    for name in names:
        if name in values and name not in start:
            start[name] = float(values[name])
    out = {}
    for position, lo, hi in zip(free, lower, upper):
        name = names[position]
        if name not in start:
            continue
        value = start[name]
        width = (hi - lo) if lo is not None and hi is not None else max(abs(value), 1.0)
        margin = 1e-6 * width
        if lo is not None and value <= lo:
            value = lo + margin
        if hi is not None and value >= hi:
            value = hi - margin
        out[name] = value
    return out


def reductions(model, names, free, lower, upper) -> list[tuple[str, dict[str, float]]]:
    """Starts where the model reduces to a smaller one it extends, from its own initial values.

    The model's nested-start rule ([`set_nested_start()`][greyid.api.Model.set_nested_start])
    says where each part the model adds to a smaller one vanishes (a sensor state
    that follows the air, a heater with no delay).  Each such part, found by asking
    the rule with one parameter left out of the initial values, gives one start:
    the initial values with that part where it vanishes.  A multi-start fit then
    also searches from the smaller models' neighbourhood, where a larger model's
    best optimum often lies (PRBS1's TiThTs: 3995 from its sensor-free start, where
    every other start of a four-start fit ends below TiTh's optimum, 3903).
    Returns ``[(label, {parameter: value}), ...]``.
    """
    rule = getattr(model, "nested_start", None)
    if rule is None:
        return []
    initial = model.initial_values()
    parts = []
    for name in names:
        try:
            changed = rule({k: v for k, v in initial.items() if k != name})
        except Exception:  # noqa: BLE001  a user's rule that cannot take these values gives no start
            continue
        part = tuple(sorted(k for k in changed if k in names))
        if name in part and part not in parts:
            parts.append(part)
    out = []
    for part in parts:
        values = {k: v for k, v in initial.items() if k not in part}
        out.append((f"reduced ({', '.join(part)} where they vanish)",
                    nested_start(model, values, names, free, lower, upper)))
    return out


__all__ = ["space_filling", "nested_start", "reductions", "NONE", "LOWER", "UPPER", "BOTH"]
