"""A fit's criterion again, with some parameters held at chosen values (profiles, posterior sampling).

[`Refit`][greyid.estimate.refit.Refit] rebuilds the estimation problem of a
[`FitResult`][greyid.api.FitResult]
— its data, filter, criterion and prior, the other parameters free within their
bounds — once, so that many constrained re-estimations (the points of a profile
likelihood) reuse the data preparation and the compiled programs of the fit.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import replace

import numpy as np

from ..errors import ModelError
from ..filters.api import prepare_datasets
from . import objective
from .estimation import FreeParameters, make_problem, new_search, single_programs, uses_scoring
from .objective import compiled
from .optimize import EXACT, GRADIENT, VALUE, Optimum, run_alone
from .settings import filter_settings
from .transforms import Transform

#: Quasi-Newton steps a refit takes before exact Newton steps take over (see Refit.optimum).
QUASI_NEWTON_STEPS = 12


def fit_data(fit) -> list:
    """The fit's data frames (read from its data file if it was loaded)."""
    frames = fit.attach_stored_data()
    if frames is None:
        raise ModelError("this fit carries no data (it was loaded from a file without one); "
                         "attach it with fit.with_data(frame)")
    return frames


class Refit:
    """The criterion of ``fit`` over its free parameters less ``held``, which take values per call.

    The held parameters stay coordinates of the fit's own problem, set to their
    values: the fit's compiled programs serve every held set (a profile of each
    parameter compiles nothing new), the derivatives restricted to the others.
    """

    def __init__(self, fit, held=(), maxiter: int = 200):
        model = fit.model
        self.structure = model.structure
        self.names = list(model.parameter_names)
        declared, params = model.parameters, fit.params
        self.theta_hat = params.loc[self.names, "estimate"].to_numpy(dtype=np.float64)
        fixed = params.loc[self.names, "fixed"].to_numpy(dtype=bool)
        free = [i for i, n in enumerate(self.names) if not fixed[i]]
        not_free = [n for n in held if n not in [self.names[i] for i in free]]
        if not_free:
            raise ModelError(f"'{not_free[0]}' is not a free parameter of this fit of model '{model.name}'")
        lower = [declared[self.names[i]].lower if self.names[i] in declared else None for i in free]
        upper = [declared[self.names[i]].upper if self.names[i] in declared else None for i in free]
        transform = Transform.from_bounds(lower, upper)
        self.parameters = FreeParameters(tuple(self.names), self.theta_hat, tuple(free), tuple(lower), tuple(upper),
                                         transform)
        s = fit.settings
        # Every setting of the fit's filter (a particle fit's particles and seed too), less where the data lie.
        rerun = {k: v for k, v in filter_settings(s).items() if k not in ("time", "hold", "time_unit", "method")}
        self.problem = make_problem(self.structure, self.parameters, s["method"],
                                    (s.get("robust"), s.get("horizon", 1), s.get("prior")), rerun)
        prepared = prepare_datasets(self.structure, self.theta_hat, fit_data(fit), s["time"], s["hold"],
                                    s.get("time_unit"), check=False)
        rows = sum(series.n_rows for series, _ in prepared)
        if rows > objective.LONG_SERIES:
            self.problem = replace(self.problem, long_series=True)
        # The shapes the fit evaluated: its compiled programs serve the refits.
        self.datasets = [inputs for _, inputs in objective.evaluated_datasets(self.problem, prepared)]
        self.scoring = uses_scoring(s.get("optimizer", "auto"), rows, len(free))
        self.maxiter = maxiter
        free_names = [self.names[i] for i in free]
        self.held = list(held)
        self.held_index = [free_names.index(n) for n in self.held]
        self.other = np.array([j for j in range(len(free)) if j not in self.held_index], dtype=int)
        self.free_names = [free_names[j] for j in self.other]
        self.z_full_hat = transform.to_z(self.theta_hat[free])
        self.z_hat = self.z_full_hat[self.other]
        self.arguments = (*self.problem.arguments(self.theta_hat), self.datasets)

    def z_full(self, z, held_values) -> np.ndarray:
        """The fit's coordinates: ``z`` for the other parameters, the held ones at their values."""
        out = np.empty(len(self.z_full_hat))
        out[self.other] = np.asarray(z, dtype=np.float64)
        out[self.held_index] = self.held_z(held_values)
        return out

    def held_z(self, held_values) -> np.ndarray:
        """The held parameters' values in the fit's coordinates."""
        transform = self.parameters.transform
        return np.array([Transform(transform.kind[j:j + 1], transform.lower[j:j + 1],
                                   transform.upper[j:j + 1]).to_z([float(value)])[0]
                         for j, value in zip(self.held_index, held_values)], dtype=np.float64)

    def theta(self, z, held_values) -> np.ndarray:
        """The full θ at z (the other free parameters) and the held values."""
        theta = self.problem.theta(self.z_full(z, held_values), self.theta_hat)
        for name, value in zip(self.held, held_values):
            theta[self.names.index(name)] = float(value)  # exactly, not through z
        return theta

    def criterion(self, z, held_values) -> float:
        """The fit's criterion (log-likelihood or log-posterior) at z and the held values."""
        value = compiled(self.structure, self.problem).value
        return -float(value(self.z_full(z, held_values), *self.arguments))

    def optimum(self, held_values, z0=None) -> Optimum:
        """The other parameters re-estimated with the held ones at ``held_values``, from ``z0``."""
        z0 = self.z_hat if z0 is None else np.asarray(z0, dtype=np.float64)
        if len(z0) == 0:  # nothing left to estimate
            f = -self.criterion(z0, held_values)
            return Optimum(z0, f, np.zeros(0), np.zeros((0, 0)), 0, 1, bool(np.isfinite(f)), "nothing to estimate")
        keep = self.other
        full = self.programs()

        def restricted(kind):
            def evaluate(z):
                out = full[kind](self.z_full(z, held_values))
                if kind == VALUE:
                    return out
                if kind == GRADIENT:
                    return out[0], np.asarray(out[1])[keep]
                f, g, H = out
                return f, np.asarray(g)[keep], np.asarray(H)[np.ix_(keep, keep)]
            return evaluate

        programs = {kind: restricted(kind) for kind in full}

        def search_from(z, hessian=None):
            search = new_search(self.problem, z, self.maxiter if hessian is None else QUASI_NEWTON_STEPS,
                                lambda *a: None, self.scoring and self.problem.long_series and hessian is None)
            search.step_limit = search.step_limit[keep] if np.ndim(search.step_limit) else search.step_limit
            search.hessian = hessian
            return run_alone(search, programs)

        # Warm starts lie near their optimum, where the Hessian changes little: quasi-Newton
        # steps from the fit's Hessian, each a gradient's cost; exact Newton steps (scoring
        # on long series) finish where they do not converge within QUASI_NEWTON_STEPS.
        quick = search_from(z0, self.hessian()[np.ix_(keep, keep)])
        if quick.converged:
            return quick
        slow = search_from(quick.z if np.isfinite(quick.value) else z0)
        return replace(slow, iterations=quick.iterations + slow.iterations,
                       evaluations=quick.evaluations + slow.evaluations)

    def predicted(self, z, held_from, held_to) -> np.ndarray:
        """The others' optimum at ``held_to`` predicted from theirs (``z``) at ``held_from``: to first
        order it moves by −H_oo⁻¹H_oh Δz_h (H the fit's Hessian; o the others, h the held ones)."""
        if len(self.other) == 0:
            return np.asarray(z, dtype=np.float64)
        z = np.asarray(z, dtype=np.float64)
        H = self.hessian()
        change = self.held_z(held_to) - self.held_z(held_from)
        try:
            move = -np.linalg.solve(H[np.ix_(self.other, self.other)], H[np.ix_(self.other, self.held_index)] @ change)
        except np.linalg.LinAlgError:
            return z
        return z + move if np.all(np.isfinite(move)) else z

    def hessian(self) -> np.ndarray:
        """The criterion's exact Hessian at the fit's estimate, in the fit's coordinates (computed once)."""
        if getattr(self, "_hessian", None) is None:
            self._hessian = np.asarray(self.programs()[EXACT](self.z_full_hat)[2])
        return self._hessian

    def programs(self) -> dict:
        """The fit's programs with their threads, opened once for every refit (closed by `close()`)."""
        if getattr(self, "_programs", None) is None:
            self._stack = ExitStack()
            self._programs = single_programs(self.structure, self.problem, self.arguments, self._stack)
            value_and_grad = compiled(self.structure, self.problem).value_and_grad
            self._programs[GRADIENT] = lambda z: value_and_grad(np.asarray(z, dtype=np.float64), *self.arguments)
        return self._programs

    def close(self) -> None:
        if getattr(self, "_programs", None) is not None:
            self._stack.close()
            self._programs = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
