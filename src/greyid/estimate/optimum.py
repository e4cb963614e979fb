"""From an optimum to a [`FitResult`][greyid.api.FitResult]: natural parameters, honest standard errors
and flags.

The uncertainty comes from the exact Hessian of the negative log-posterior at the
optimum (section 3.3.2), mapped from the optimiser's coordinates to the natural
parameters; a singular or indefinite Hessian is reported by the parameter
combination it leaves undetermined, a parameter at a bound loses its standard
error, and a fit converges only at a minimum ([`honest_convergence()`][greyid.estimate.optimum.honest_convergence]).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import special

from ..errors import warn as warn_user
from ..model.parameters import equation_expressions
from .covariance import FEW_STEPS, parameter_covariance
from .calls import loglik_at
from .results import Estimates, FitWarning, parameter_table
from .settings import filter_settings

#: Eigenvalues of the scaled Hessian below this fraction of the largest are ill-determined.
ILL_DETERMINED = 1e-8
#: A standard error above this multiple of max(|estimate|, 1) marks a nearly flat likelihood.
FLAT_SE = 100.0


#: Largest change of the criterion from moving an interior parameter by one standard
#: error along its gradient that a converged fit may leave.
GRADIENT_ACROSS_SE = 1e-2


def honest_convergence(best, ill, free_names, inner, g_theta, se) -> tuple[bool, str]:
    """Converged only at a minimum: the optimiser says so, the Hessian of the parameters not at a
    bound is positive definite, and no interior gradient is large on the scale of its standard error."""
    if not best.converged:
        return False, best.message
    reasons = []
    if ill:
        flat = sorted({name for d in ill for name in d["direction"]})
        reasons.append("the Hessian is not positive definite: flat or curved-down direction in "
                       + ", ".join(flat))
    steep = [f"{n} (|g|·SE = {abs(g) * e:.2g})" for n, i, g, e in zip(free_names, inner, g_theta, se)
             if i and np.isfinite(g) and np.isfinite(e) and abs(g) * e > GRADIENT_ACROSS_SE]
    if steep:
        reasons.append("the gradient is not small for " + ", ".join(steep))
    if reasons:
        return False, "stopped where " + "; ".join(reasons)
    return True, best.message


def why_undetermined(model, name: str, frames) -> str:
    """``"; it enters the equations only with the input 'u', which is 0 in every row"`` where the
    inputs that are constant in the data make every equation independent of parameter ``name``,
    else ``""``."""
    import sympy as sp

    structure = model.structure
    constant = {}
    for column in structure.input_names:
        values = np.concatenate([np.asarray(df[column], dtype=float) for df in frames if column in df])
        values = values[np.isfinite(values)]
        if len(values) and np.all(values == values[0]):
            constant[column] = float(values[0])
    if not constant:
        return ""
    entries = equation_expressions(structure)
    symbol = next((s for e in entries for s in e.free_symbols if s.name == name), None)
    if symbol is None:
        return ""
    slopes = [sp.diff(e, symbol) for e in entries]
    with_inputs = sorted({s.name for d in slopes for s in d.free_symbols if s.name in constant})
    if not with_inputs:
        return ""
    values = {s: sp.nsimplify(constant[s.name]) for d in slopes for s in d.free_symbols if s.name in constant}
    if any(sp.simplify(d.subs(values)) != 0 for d in slopes):
        return ""
    said = ", ".join(f"'{n}' ({constant[n]:g} in every row)" for n in with_inputs)
    return f"; it enters the equations only with the constant input{'s' if len(with_inputs) > 1 else ''} {said}"


def build_result(model, frames, theta, problem, best, optima, settings, scores=None) -> Estimates:
    """Map the optimum back to natural parameters and compute the uncertainty.

    ``scores`` is the [`ScoreCovariance`][greyid.estimate.covariance.ScoreCovariance] of the per-step scores in z,
    needed for ``cov_type`` "opg" and "sandwich".
    """
    names = list(model.parameter_names)
    free = list(problem.free)
    free_names = [names[i] for i in free]
    transform = problem.transform
    d1 = transform.derivative(best.z)
    theta_free = theta[free]
    warn = []
    at_bound = transform.at_bound(best.z, best.gradient, np.diag(best.hessian))
    g_theta = np.where(at_bound, np.nan, best.gradient / np.where(at_bound, 1.0, d1))
    # H_z = J H_θ J + diag(g_θ θ''); at the optimum g_θ = 0 for interior parameters, so
    # H_θ = J⁻¹ H_z J⁻¹.  (Keeping the g_θ θ'' term would only add the optimiser's
    # residual gradient, which can mask an exactly singular direction.)
    inner = ~at_bound
    Hz = 0.5 * (best.hessian + best.hessian.T)
    Jinv = 1.0 / d1[inner]
    H = Hz[np.ix_(inner, inner)] * np.outer(Jinv, Jinv)
    # A criterion that does not depend on a parameter at all has exactly zero slope and curvature in
    # it (JAX differentiates an absent term to 0.0): wherever the search left it (at a bound, or
    # inside where rounding in the other parameters' steps moved it), the data simply do not
    # determine it.  Where dθ/dz has underflowed, z's derivatives are 0 whatever θ's are, and only
    # the equations can tell (the constant inputs that leave the parameter out).
    flat_in_z = (best.gradient == 0.0) & np.all(best.hessian == 0.0, axis=1)
    why = {i: why_undetermined(model, free_names[i], frames) for i in np.flatnonzero(flat_in_z)}
    independent = np.array([i in why and (abs(d1[i]) > 0 or bool(why[i])) for i in range(len(free))], dtype=bool)
    explained = {free_names[i] for i in np.flatnonzero(independent)}
    for i in np.flatnonzero(at_bound & ~independent):
        warn.append(f"parameter '{free_names[i]}' is at a bound ({theta_free[i]:.6g}); "
                    "its standard error is not given")
    for i in np.flatnonzero(independent):
        where = ", at a bound" if at_bound[i] else ""
        warn.append(f"the likelihood does not depend on '{free_names[i]}' (its slope and curvature are 0)"
                    f"{why[i]}: the data do not determine it, and its estimate ({theta_free[i]:.6g}{where}) "
                    "means nothing")

    k = int(inner.sum())
    cov_inner = np.full((k, k), np.nan)
    reliable = np.ones(len(free), dtype=bool)
    ill = []
    if k:
        scale = np.sqrt(np.abs(np.diag(H)))
        scale = np.where(scale > 0, scale, 1.0)
        Hs = H / np.outer(scale, scale)
        w, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
        bad = w <= ILL_DETERMINED * max(w.max(), 1e-300)
        inner_names = [n for n, b in zip(free_names, inner) if b]
        for j in np.flatnonzero(bad):
            # Loadings in standardized units (each parameter scaled by its curvature), so
            # that a ridge such as a·b = const names both a and b wherever along it the fit ends.
            vec = V[:, j] / np.max(np.abs(V[:, j]))
            loading = {inner_names[i]: float(vec[i]) for i in np.argsort(-np.abs(vec)) if abs(vec[i]) > 0.05}
            ill.append({"eigenvalue": float(w[j]), "direction": loading})
            for name in loading:
                reliable[free_names.index(name)] = False
            if set(loading) <= explained:
                continue  # said above: the likelihood does not depend on it
            desc = ", ".join(f"{v:+.3f}·{n}" for n, v in loading.items())
            why = why_undetermined(model, next(iter(loading)), frames) if len(loading) == 1 else ""
            warn.append(f"the Hessian is {'singular' if w[j] > -1e-12 else 'not positive definite'} in the "
                        f"direction {desc}{why}: these parameters are not determined by the data, "
                        "their standard errors are unreliable (greyid.design.identifiability(model) says "
                        "whether any experiment could determine them, and which combination it can)")
        J = None if scores is None else scores.matrix[np.ix_(inner, inner)] * np.outer(Jinv, Jinv)
        if scores is not None:
            for name, steps in zip(inner_names, scores.effective_steps[inner]):
                if steps < FEW_STEPS:
                    reliable[free_names.index(name)] = False
                    warn.append(f"the {settings['cov_type']} standard error of '{name}' rests on about "
                                f"{steps:.1f} observations' scores (an initial state?); it is unreliable")
        cov_inner = parameter_covariance(H, J, settings.get("cov_type", "hessian"), bool(bad.any()))

    cov = np.full((len(free), len(free)), np.nan)
    idx = np.flatnonzero(inner)
    cov[np.ix_(idx, idx)] = cov_inner
    se = np.sqrt(np.where(np.diag(cov) >= 0, np.diag(cov), np.nan))
    # A parameter along a flat direction the data do not determine has no finite standard error (the
    # pseudo-inverse leaves that direction out: its diagonal would look small, even 0): as for a
    # Cramér–Rao bound, it is infinite (t = 0, p = 1), while fit.cov keeps what the data do
    # determine (a combination's variance by Gauss' formula).
    for direction in ill:
        # Flat (singular) directions only: along a negative curvature the fit is at no maximum,
        # and its standard errors are unreliable rather than infinite.
        if abs(direction["eigenvalue"]) <= ILL_DETERMINED * len(free):
            for name in direction["direction"]:
                se[free_names.index(name)] = np.inf
    for j in np.flatnonzero(inner & reliable & (se > FLAT_SE * np.maximum(np.abs(theta_free), 1.0))):
        # Not singular to working precision, yet the data barely constrain it (a noise
        # intensity drifting towards −∞ with SE 7863): as unreliable as a singular direction.
        reliable[j] = False
        warn.append(f"the likelihood is nearly flat in '{free_names[j]}' (standard error {se[j]:.4g} against "
                    f"an estimate of {theta_free[j]:.4g}): the data do not determine it")
    n_obs = int(sum(np.count_nonzero(~np.isnan(df[name].to_numpy(dtype=float)))
                    for df in frames for name in model.output_names))
    dof = max(n_obs - len(free), 1)  # as Estimates.df_resid
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero standard error: no test
        tval = np.where(se > 0, theta_free / np.where(se > 0, se, 1.0), np.nan)
    pval = 2 * special.stdtr(dof, -np.abs(tval))  # two-sided Student-t p-value
    # A flat direction in parameters the likelihood does not depend on is explained by that alone.
    unexplained = [d for d in ill if not set(d["direction"]) <= explained]
    converged, message = honest_convergence(best, unexplained, free_names, inner, g_theta, se)
    if independent.any():
        said = ("the data do not determine " + ", ".join(f"'{free_names[i]}'" for i in np.flatnonzero(independent))
                + " (the likelihood does not depend on it)")
        message = said if converged else f"{said}; {message}"
        converged = False
    if not converged:
        warn.append(f"the fit did not converge: {message}")
    if settings.get("substeps_accurate") is False:
        warn.append(f"the filter is not accurate between samples: {settings['substep_note']}")

    params = parameter_table(model, theta, free, se, t_value=tval, p_value=pval, at_bound=at_bound,
                             reliable=reliable & ~at_bound, gradient=-g_theta)

    criterion_value = -best.value
    simple = settings["criterion"] == "ml" and not settings["robust"] and settings["horizon"] == 1
    if simple:
        loglik = criterion_value
    else:
        loglik = loglik_at(model, dict(zip(names, theta)), frames if len(frames) > 1 else frames[0],
                           **filter_settings(settings))
    for text in warn:  # printed plainly once, and kept on the fit
        warn_user(f"{model.name}: {text}", FitWarning)
    return Estimates(model=model, params=params, cov=pd.DataFrame(cov, index=free_names, columns=free_names),
                     loglik=float(loglik), criterion_value=float(criterion_value), n_obs=n_obs,
                     converged=converged, message=message, iterations=best.iterations,
                     settings=settings, warnings=warn, ill_determined=ill, data=frames,
                     start_values=[float(-o.value) for o in optima],
                     starts=[dict(start=label, criterion=float(-o.value), converged=bool(o.converged),
                                  iterations=int(o.iterations), message=o.message)
                             for label, o in zip(settings.get("start_labels", []), optima)])
