"""From a [`Model`][greyid.api.Model]'s equations to its compiled
[`Structure`][greyid.model.structure.Structure].

The equations are checked against each other (names declared once, noise only
in system equations, the initial state free of states and inputs), algebraic
definitions are substituted, each ``delay(u, tau)`` becomes an extra input of
the model functions, parameters are ordered as they first appear, the model
class (4.1.4) is found, and every part is lambdified into JAX.
"""

from __future__ import annotations

import hashlib
import re

import numpy as np
import sympy as sp

from ..errors import ModelError
from .delays import find_delays
from .distributions import NORMAL, Distribution
from .equations import CONSTANTS, is_wiener_name
from .symbols import TIME
from .latent import augment
from .transforms import initial_mean_and_covariance, lamperti, state_transforms
from .structure import (LTI, NONLINEAR, InitialCovariance, Structure, classify, lambdify_model, lambdify_parameters,
                        linear_drift_function, observation_is_constant)


def build_structure(model) -> Structure:
    """The structure of a model written as equations (model (4.1)–(4.2))."""
    if not model._system and not model._latent_forces:
        raise ModelError("the model has no system equations; add them with add_system() (or a latent force with "
                         "add_latent_force())")
    if not model._observations:
        raise ModelError("the model has no observation equation; add one with add_observation()")
    states = [e.state for e in model._system]
    inputs = list(model._inputs)
    outputs = [o[0].lhs for o in model._observations]
    clash = set(states) & set(inputs)
    if clash:
        raise ModelError(f"'{sorted(clash)[0]}' is declared both as a state and as an input")
    for a in model._algebraics:
        if a.lhs in states or a.lhs in inputs:
            raise ModelError(f"algebraic equation '{a.text}' redefines the state or input '{a.lhs}'")
    for o in outputs:
        if o in states or o in inputs:
            raise ModelError(f"observation name '{o}' is already a state or an input; give the output another name")

    sub = model._substitute_algebraics
    drift = [sub(e.drift) for e in model._system]
    noise_names = sorted({w for e in model._system for w in e.diffusion})
    diffusion = [[sub(e.diffusion.get(w, sp.Integer(0))) for w in noise_names] for e in model._system]
    observation = [sub(o[0].rhs) for o in model._observations]
    variance = [sub(o[1]) for o in model._observations]
    laws = [model._distributions.get(o, Distribution(NORMAL)) for o in outputs]
    families = tuple(law.family for law in laws)
    # Each output's shape parameter (df, size, trials), 1 where its family has none.
    shapes = [sub(model._expression(1.0 if law.shape is None else law.shape, f"{law.shape_name} of '{o}'"))
              for law, o in zip(laws, outputs)]
    for entry, h in zip(model._observations, observation):
        # 'y = a + b*u + 0*x' (a static regression, on purpose) is a + b*u to SymPy: the text still
        # names the state, as '0*dt' does for a state without drift.
        written = {name for name in re.findall(r"[A-Za-z_]\w*", entry[0].text.split("=", 1)[1])}
        if not ({s.name for s in h.free_symbols} | written) & (set(states) | set(model._latent_forces)):
            uses = sorted(s.name for s in h.free_symbols if s.name not in inputs and s != TIME)
            which = f" (it uses {', '.join(repr(u) for u in uses)}, not a state)" if uses else ""
            raise ModelError(f"observation '{entry[0].text}' depends on no state{which}: it says nothing of the "
                             f"system's dynamics; an observation must be a function of the states {states}")

    correlation = observation_covariance_expressions(model, outputs, variance, states)
    mean_exprs, cov = initial_state_expressions(model, states) if states else ([], [])
    mean_exprs = [sub(e) for e in mean_exprs]
    if isinstance(cov, list):
        cov = [[sub(e) for e in row] for row in cov]

    transforms, maps, ode_drift = dict(model._transforms), {}, None
    if transforms:  # Lamperti transforms: every expression in the transformed states' coordinates
        drift, diffusion, (observation, variance, shapes), maps, ode_drift = lamperti(
            states, transforms, drift, diffusion, [observation, variance, shapes], noise_names)
        mean_exprs, cov = initial_mean_and_covariance(states, transforms, maps, mean_exprs, cov)

    # Latent forces: their kernels' states after the model's own, each force's H z put for its name.
    augmented = augment(model, states, noise_names, drift, diffusion,
                        [observation, variance, shapes, ode_drift or []])
    own = len(states)
    states, noise_names, drift, diffusion = (augmented.states, augmented.noise_names, augmented.drift,
                                             augmented.diffusion)
    observation, variance, shapes, ode_rows = augmented.others
    ode_drift = None if ode_drift is None else ode_rows + drift[own:]  # the forces' states have no Itô term
    latent_cov = augmented.latent_covariance
    if latent_cov is not None:
        mean_exprs = mean_exprs + [sp.Integer(0)] * latent_cov.shape[0]
        if isinstance(cov, list):  # a given matrix: the forces' stationary block beside it
            cov = sp.diag(sp.Matrix(cov) if cov else sp.zeros(0, 0), latent_cov).tolist()

    known = {sp.Symbol(n, real=True) for n in states + inputs} | {TIME}
    everything = [*drift, *[g for row in diffusion for g in row], *observation, *variance, *shapes, *mean_exprs,
                  *([] if latent_cov is None else list(latent_cov)),
                  *([] if correlation is None else [e for row in correlation for e in row])]
    if isinstance(cov, list):
        everything += [e for row in cov for e in row]
    for e, where in [(x, "initial state") for x in mean_exprs] + [(v, "observation variance") for v in variance]:
        bad = [s.name for s in e.free_symbols if s.name in states or s.name in inputs or s == TIME]
        if where == "initial state" and bad:
            raise ModelError(f"the initial state cannot depend on '{bad[0]}'")
    for e in everything:
        wieners = [s.name for s in e.free_symbols if is_wiener_name(s.name)]
        if wieners:
            raise ModelError(f"'{wieners[0]}' appears outside a system equation's noise term")

    # delay(u, tau) → a stand-in input; tau's parameters are the model's parameters too.
    delays = find_delays(everything, inputs, states)
    initial = [*mean_exprs, *([e for row in cov for e in row] if isinstance(cov, list) else [])]
    outside = find_delays(initial, inputs, states)
    if outside:
        raise ModelError(f"'{outside[0][1].name}' may appear in system and observation equations, "
                         "not in the initial state")
    replace = {call: stand_in for call, _, stand_in in delays}
    drift, observation, variance, shapes = ([e.xreplace(replace) for e in part]
                                            for part in (drift, observation, variance, shapes))
    diffusion = [[g.xreplace(replace) for g in row] for row in diffusion]
    ode_drift = None if ode_drift is None else [e.xreplace(replace) for e in ode_drift]

    ordered: list[str] = []
    stand_ins = set(replace.values())
    for e in [*everything, *[d.expression for _, d, _ in delays]]:
        for s in sorted(e.free_symbols - known - stand_ins, key=lambda s: s.name):
            if s.name not in ordered:
                ordered.append(s.name)
    unknown_declared = sorted(set(model._parameters) - set(ordered))
    if unknown_declared:
        name = unknown_declared[0]
        if name in CONSTANTS:
            raise ModelError(f"parameter '{name}' is declared, but '{name}' in an equation is the constant "
                             f"{CONSTANTS[name]}: give the parameter another name")
        if name in inputs:
            raise ModelError(f"parameter '{name}' is declared, but '{name}' is an input of the model: give the "
                             "parameter another name (or remove it from the inputs)")
        if name in states:
            raise ModelError(f"parameter '{name}' is declared, but '{name}' is a state of the model: give the "
                             "parameter another name")
        raise ModelError(f"parameter '{name}' is declared but does not appear in the model")
    state_syms = [sp.Symbol(n, real=True) for n in states]
    input_syms = [sp.Symbol(n, real=True) for n in inputs] + [stand_in for _, _, stand_in in delays]
    param_syms = [sp.Symbol(n, real=True) for n in ordered]
    delayed = tuple(type(d)(d.name, d.input, d.expression, lambdify_parameters([d.expression], param_syms, ()))
                    for _, d, _ in delays)

    f_mat, g_mat = sp.Matrix(drift), sp.Matrix(diffusion) if noise_names else sp.zeros(len(states), 0)
    h_mat, s_mat = sp.Matrix(observation), sp.Matrix(variance)
    kind = classify(f_mat, g_mat, h_mat, s_mat, state_syms, input_syms)
    # The dynamics alone may be linear and time-invariant where the observations are not.
    dynamics = kind if kind == LTI else classify(f_mat, g_mat, sp.Matrix(state_syms[:1]), sp.Matrix([0]),
                                                 state_syms, input_syms)
    linear_dynamics = linear_drift_function(f_mat, state_syms, input_syms, param_syms) if dynamics == LTI else None
    # The outputs' noise covariances where they are correlated, delays replaced as above.
    covariances = [] if correlation is None else [e.xreplace(replace) for row in correlation for e in row]
    n, m, s = len(states), len(noise_names), len(outputs)
    args = (state_syms, input_syms, param_syms)
    flat_g = [g for row in diffusion for g in row]
    diffuse = tuple(states.index(x) for x in model._diffuse)
    if diffuse and kind == NONLINEAR:
        raise ModelError(f"the diffuse initial state {list(model._diffuse)} needs a linear model (the exact diffuse "
                         "start is a Kalman filter's), but this model is nonlinear; give those states a mean and a "
                         "covariance instead")
    seen_by = outputs_seeing(f_mat, h_mat, state_syms, diffuse)
    for i, outputs_of_state in zip(diffuse, seen_by):
        if not outputs_of_state:
            raise ModelError(f"diffuse state '{states[i]}' is seen by no output (directly or through the states it "
                             "drives): its initial value cannot be determined; give it a mean and a covariance")
    if isinstance(cov, list):
        cov_fn = lambdify_parameters([e for row in cov for e in row], param_syms, (n, n))
        initial_cov = InitialCovariance("matrix", matrix=cov_fn, diffuse=diffuse, seen_by=seen_by)
    else:
        latent = None if latent_cov is None else lambdify_parameters(list(latent_cov), param_syms, latent_cov.shape)
        initial_cov = InitialCovariance(cov, scale=model._initial_scale, latent=latent, latent_start=augmented.start,
                                        diffuse=diffuse, seen_by=seen_by)
    fingerprint = structure_fingerprint(
        states, input_syms, outputs, ordered, noise_names, kind, drift, flat_g, observation, variance,
        covariances, mean_exprs, cov if isinstance(cov, list) else (cov, model._initial_scale), diffuse,
        [(d.name, d.input, d.expression) for d in delayed], families, shapes, sorted(transforms.items()),
        None if latent_cov is None else (list(latent_cov), [(f.name, f.indices, f.weights) for f in augmented.forces]))
    return Structure(
        state_names=tuple(states),
        input_names=tuple(inputs),
        output_names=tuple(outputs),
        parameter_names=tuple(ordered),
        noise_names=tuple(noise_names),
        kind=kind,
        drift=lambdify_model(drift, *args, (n,)),
        diffusion=lambdify_model(flat_g, *args, (n, m)) if m else zero_diffusion(n),
        observation=lambdify_model(observation, *args, (s,)),
        observation_variance=lambdify_model(variance, *args, (s,)),
        initial_mean=lambdify_parameters(mean_exprs, param_syms, (n,)),
        initial_covariance=initial_cov,
        equations=dict(drift=f_mat, diffusion=g_mat, observation=h_mat, variance=s_mat,
                       covariance=sp.Matrix(covariances)),
        observation_covariance=None if correlation is None else lambdify_model(covariances, *args, (s, s)),
        delays=delayed,
        constant_observation=observation_is_constant(h_mat, [*variance, *covariances], state_syms, input_syms),
        linear_drift=linear_dynamics if kind == LTI else None,
        fingerprint=fingerprint,
        linear_dynamics=linear_dynamics,
        distributions=families if any(f != NORMAL for f in families) else (),
        observation_shape=None if all(f == NORMAL for f in families) else lambdify_model(shapes, *args, (s,)),
        state_transforms=state_transforms(states, transforms, maps, ordered),
        ode_drift=None if ode_drift is None else lambdify_model(ode_drift, *args, (n,)),
        latent_forces=augmented.forces,
    )


def outputs_seeing(f_mat, h_mat, state_syms, states: tuple[int, ...]) -> tuple[tuple[int, ...], ...]:
    """For each of ``states``, the outputs whose equation depends on it, directly or through the states whose
    drift it enters (and so on): the outputs that can determine its initial value."""
    n = len(state_syms)
    drives = [[k for k in range(n) if f_mat[k].has(state_syms[i])] for i in range(n)]
    seen = []
    for i in states:
        reached, frontier = {i}, [i]
        while frontier:
            for k in drives[frontier.pop()]:
                if k not in reached:
                    reached.add(k)
                    frontier.append(k)
        seen.append(tuple(j for j in range(h_mat.shape[0])
                          if any(h_mat[j].has(state_syms[k]) for k in reached)))
    return tuple(seen)


def structure_fingerprint(*parts) -> str:
    """A hash of the expressions as lambdified and of the names and settings around them.

    ``srepr`` writes every symbol with its assumptions, so equal hashes mean equal
    model functions.
    """
    def text(part):
        if isinstance(part, sp.Basic):
            return sp.srepr(part)
        if isinstance(part, (list, tuple)):
            return "[" + ", ".join(text(p) for p in part) + "]"
        return repr(part)

    return hashlib.sha256(text(parts).encode()).hexdigest()


def zero_diffusion(n: int):
    import jax.numpy as jnp

    return lambda x, u, t, theta: jnp.zeros((n, 0))


def observation_covariance_expressions(model, outputs, variance, states):
    """The checked full observation covariance (SymPy rows), or None for independent outputs."""
    if model._observation_covariance is None:
        return None
    rows = model._observation_covariance
    s = len(outputs)
    if len(rows) != s or any(len(r) != s for r in rows):
        raise ModelError(f"the observation covariance must be {s}x{s} (outputs {outputs})")
    exprs = [[model._substitute_algebraics(model._expression(v, f"observation covariance of '{outputs[i]}' and "
                                                                f"'{outputs[j]}'")) for j, v in enumerate(r)]
             for i, r in enumerate(rows)]
    for i in range(s):
        if sp.simplify(exprs[i][i] - variance[i]) != 0:
            raise ModelError(f"the observation covariance's diagonal entry for '{outputs[i]}' is {exprs[i][i]}, "
                             f"but its variance is {variance[i]}; they must agree")
        for j in range(i + 1, s):
            if sp.simplify(exprs[i][j] - exprs[j][i]) != 0:
                raise ModelError(f"the observation covariance is not symmetric for '{outputs[i]}' and "
                                 f"'{outputs[j]}'")
    used = {sym.name for row in exprs for e in row for sym in e.free_symbols}
    if used & set(states):
        raise ModelError(f"the observation covariance cannot depend on the state '{sorted(used & set(states))[0]}'")
    return exprs


def initial_state_expressions(model, states: list[str]):
    """The initial mean (SymPy, per state) and the covariance: SymPy rows or its kind's name."""
    if model._initial_mean is None:
        raise ModelError("the model has no initial state: give it a [model.initial_state] table in a model file "
                         "(a value or parameter per state), or set_initial_state(mean={...}) in Python")
    unknown = [k for k in model._initial_mean if k not in states]
    if unknown:
        raise ModelError(f"initial state given for '{unknown[0]}', which is not a state (states: {states})")
    missing = [x for x in states if x not in model._initial_mean and x not in model._diffuse]
    if missing:
        raise ModelError(f"initial state mean missing for state '{missing[0]}'")
    model._checked_diffuse(model._diffuse, model._initial_mean, model._initial_covariance, states)
    mean = [model._expression(model._initial_mean.get(x, 0.0), f"initial state of '{x}'") for x in states]
    cov = model._initial_covariance
    if isinstance(cov, str):
        return mean, cov
    n = len(states)
    try:
        arr = np.asarray(cov, dtype=object)
    except Exception:  # ragged lists
        raise ModelError(f"initial covariance must be an {n}x{n} matrix") from None
    if arr.ndim == 1 and arr.shape == (n,):
        arr = np.diag(arr).astype(object)
        arr[arr == 0] = 0.0
    if arr.shape != (n, n):
        raise ModelError(f"initial covariance has shape {arr.shape}, but the model has {n} states: it must be {n}x{n}")
    rows = [[model._expression(arr[i, j], f"initial covariance entry ({states[i]}, {states[j]})") for j in range(n)]
            for i in range(n)]
    return mean, rows
