"""The Laplace approximation of a member's marginal likelihood, and its exact derivatives.

For member i with data y_i and standardised random effects u_i ~ N(0, I)
(η_i = L u_i, [`spec`][greyid.population.spec]),

    g_i(u, φ) = −log p(y_i | θ_i(φ, u)) + ½ uᵀu,

with −log p(y_i | θ) the member's exact filter likelihood (3.18).  The
conditional mode û_i minimises g_i, H_i = ∂²g_i/∂u² there, and

    −log L_i(φ) ≈ ℓ_i(φ) = g_i(û_i, φ) + ½ log det H_i(û_i, φ)

(the normalising constants of N(0, I) and of the Gaussian integral cancel).
Where θ_i enters the outputs linearly and the filter is exact, g_i is
quadratic in u and the approximation is exact.

Derivatives in φ (exact, by implicit differentiation).  With z = (u, φ),
F(z) = g_i + ½ log det H_i and G(z) = ∇_u g_i, the mode û(φ) solves G = 0, so
along z(φ) = (û(φ), φ) with T = dz/dφ = [û'; I] and û' = −H⁻¹ G_φ:

    ℓ_i'  = F_z T,
    ℓ_i'' = Tᵀ F_zz T + F_u û'',   H û''_{·jk} = −G_zz[T_{·j}, T_{·k}].

(At the mode F_u is the log-determinant's slope alone: the envelope theorem for
g_i.)  With λ = −H⁻¹F_uᵀ the second term is λᵀG_zz[T, T], so

    ℓ_i'' = ∂²/∂s² [F + λᵀG](z + Ts) at s = 0,

the second derivatives of one scalar along T's p columns; the gradient's program
returns T and λ with ℓ_i', and the Hessian's program takes them.

The filter enters all of this through one function of few arguments.  The member's
parameters are θ_i = θ(ψ_i), ψ_i = spec.scale(φ, u, x) the free parameters' scales
(log θ for a lognormal random effect), where u moves only the random effects'
scales ψ_R, by L u.  With K(ψ) = −log p(y_i | θ(ψ)) and

    P(ψ) = (K, ∇_R K, ∇²_R K):   g = K + ½uᵀu,  G = Lᵀ∇_R K + u,  H = Lᵀ∇²_R K L + I,

so F and G are closed-form functions of P and z.  Their first (second)
derivatives in z at a point are exact from P's Taylor polynomial of degree 1 (2)
in ψ there: the gradient's program takes P and its derivatives along the n free
parameters' scales (forward mode), the Hessian's its second derivatives too, and
everything else is differentiated in closed form.  The filter's derivatives are
thus taken along n directions rather than the q + p of z (p counts the covariate
effects and the random effects' spread too; the figures are in docs/performance.md,
``benchmarks/population.py``).
"""

from __future__ import annotations

from typing import NamedTuple, Callable

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.jit import jit, kept_key
from ..estimate.criteria import log_criterion
from ..estimate.lbfgs import DIFFERENCE_STEP, conditional_scales
from ..filters.api import compiled_filter


class LaplacePrograms(NamedTuple):
    """Compiled functions vectorised over members (leading axis of u, x, ψ, P and the data).

    Each evaluation is ``scales`` (ψ_i at the members' u), a program of the filter at ψ, then a closed
    form: ``likelihood`` then ``value``; ``on_random`` then ``inner``; ``slopes`` then ``gradient``;
    ``curvatures`` then ``hessian``.  The filter's programs depend on the population's layout only through
    where its random effects sit among the free parameters
    ([`PopulationSpec.scale_key()`][greyid.population.spec.PopulationSpec.scale_key]): nested models (a
    diagonal or a full Ω, with or without covariate effects) share them, compiled once.
    """

    scales: Callable  # (φ, u, x, base) -> ψ_i
    likelihood: Callable  # (ψ, base, data) -> K
    on_random: Callable  # (ψ, base, data) -> P = (K, ∇_R K, ∇²_R K)
    slopes: Callable  # (ψ, base, data) -> (P, ∂P/∂ψ)
    curvatures: Callable  # (ψ, base, data) -> (P, ∂P/∂ψ, ∂²P/∂ψ²)
    value: Callable  # (u, K) -> g_i
    inner: Callable  # (u, φ, P) -> (g_i, ∇_u g_i, ∇²_u g_i)
    gradient: Callable  # (φ, û, x, base, ψ, P, ∂P/∂ψ) -> (ℓ_i, ∂ℓ_i/∂φ, T_i, λ_i)
    hessian: Callable  # (φ, û, T, λ, x, base, ψ, P, ∂P/∂ψ, ∂²P/∂ψ²) -> ∂²ℓ_i/∂φ²
    shaped: Callable  # (members, order) -> zeros shaped as ψ and (P, …, its derivatives of that order)


def value_gradient_hessian(fun):
    """``fun(u) -> (value, gradient, Hessian)``, forward over forward (few random effects)."""
    def with_value(u):
        v = fun(u)
        return v, v

    def gradient(u):
        g, v = jax.jacfwd(with_value, has_aux=True)(u)
        return g, (g, v)

    def all_three(u):
        H, (g, v) = jax.jacfwd(gradient, has_aux=True)(u)
        return v, g, H

    return all_three


def _log_det(H):
    """log det of a symmetric positive definite H; NaN where it is not."""
    L = jnp.linalg.cholesky(0.5 * (H + H.T))
    return 2.0 * jnp.sum(jnp.log(jnp.diag(L)))


def build(structure, spec, options) -> LaplacePrograms:
    """The programs of one population problem: the model's filter (``options``) inside g_i.

    The outer derivatives are taken forward (along the members' free parameters' scales,
    module doc): reverse mode through the nested derivatives of the filter's scan compiles
    several times slower and runs no faster.
    """
    run = compiled_filter(structure, options, keep_outputs=False).__wrapped__
    q = spec.n_random

    def negative_loglik(theta, data):
        return -log_criterion(run(theta, data)[0])

    # The filter enters through the member's likelihood K(ψ) = −log p(y | θ(ψ)) as a function of its free
    # parameters' scales ψ = spec.scale(φ, u, x) (module doc): P(ψ) = (K, ∇_R K, ∇²_R K), R the random
    # effects' scales, and P's derivatives in ψ.  These programs depend on the population's layout only
    # through R, so nested layouts share them; everything else is closed form.
    R = jnp.asarray(spec.random_in_scale, dtype=int)

    def likelihood(psi, base, data):
        """K(ψ)."""
        return negative_loglik(spec.theta_at_scale(psi, base), data)

    def with_aux(fun):
        def wrapped(*args):
            out = fun(*args)
            return out, out
        return wrapped

    def on_random(psi, base, data):
        """P(ψ) = (K, ∇_R K, ∇²_R K) at ψ."""
        def at(v):
            return likelihood(psi.at[R].set(v), base, data)
        return value_gradient_hessian(at)(psi[R])

    def with_slopes(psi, base, data):
        """(P, ∂P/∂ψ) at ψ, forward along the n free parameters' scales."""
        P1, P0 = jax.jacfwd(with_aux(on_random), has_aux=True)(psi, base, data)
        return P0, P1

    def curvatures(psi, base, data):
        """(P, ∂P/∂ψ, ∂²P/∂ψ²) at ψ: P's second derivatives along the n free parameters' scales too."""
        def first(at):
            P0, P1 = with_slopes(at, base, data)
            return P1, (P0, P1)

        P2, (P0, P1) = jax.jacfwd(first, has_aux=True)(psi)
        return P0, P1, P2

    def value(u, K):
        """g_i = K + ½uᵀu."""
        return K + 0.5 * jnp.sum(u ** 2)

    def inner(u, phi, P):
        """(g_i, G = ∇_u g_i, H = ∂G/∂u) at (u, φ) from P at ψ_i(u): g = K + ½uᵀu, G = Lᵀ∇_R K + u and
        H = Lᵀ∇²_R K L + I (ψ_R moves with L u)."""
        K, K_R, K_RR = P
        L = spec.cholesky(phi)
        return value(u, K), L.T @ K_R + u, L.T @ K_RR @ L + jnp.eye(q)

    def parts(P, z):
        """(F, G) at z = (u, φ) from P at the member's ψ: F = g + ½ log det H, G = ∇_u g (see ``inner``)."""
        g, G, H = inner(z[:q], z[q:], P)
        return g + 0.5 * _log_det(H), G

    def taylor(P0, P1, P2, z, psi, x, base):
        """P at ψ(z) by its Taylor polynomial at ``psi`` of degree 1 (without P2) or 2: exact in value and
        in derivatives up to that degree at the z where ψ(z) = ``psi``."""
        step = spec.scale(z[q:], z[:q], x, base) - psi
        if P2 is None:
            return jax.tree_util.tree_map(lambda a, b: a + b @ step, P0, P1)
        return jax.tree_util.tree_map(lambda a, b, c: a + b @ step + 0.5 * (c @ step) @ step, P0, P1, P2)

    def path(Gz):
        """T = dz/dφ along the mode, and H = ∂G/∂u."""
        H = Gz[:, :q]
        slope = -jnp.linalg.solve(H, Gz[:, q:])
        return jnp.concatenate([slope, jnp.eye(Gz.shape[1] - q)]), H

    def gradient(phi, u_hat, x, base, psi, P0, P1):
        """ℓ_i, ℓ_i' = F_z T, and the path's tangents T and multipliers λ = −H⁻¹F_uᵀ for the Hessian, from P
        and its first derivatives at ψ_i = ``psi`` (F and G exact to first order there)."""
        z = jnp.concatenate([u_hat, phi])
        (Fz, Gz), (F, _) = jax.jacfwd(with_aux(lambda v: parts(taylor(P0, P1, None, v, psi, x, base), v)),
                                      has_aux=True)(z)
        T, H = path(Gz)
        return F, Fz @ T, T, -jnp.linalg.solve(H, Fz[:q])

    def hessian(phi, u_hat, T, lam, x, base, psi, P0, P1, P2):
        """ℓ_i'' = ∂²/∂s² [F + λᵀG](z + Ts) at s = 0, T and λ from ``gradient`` at the same φ and modes:
        the filter's second derivatives along the n scales (P's, which make F and G exact to second
        order), the closed form's along T's p columns."""
        z = jnp.concatenate([u_hat, phi])

        def along(step):
            v = z + T @ step
            F, G = parts(taylor(P0, P1, P2, v, psi, x, base), v)
            return F + lam @ G

        return jax.hessian(along)(jnp.zeros(T.shape[1]))

    def shaped(members: int, order: int):
        """Zeros shaped as ψ and as (P, ∂P/∂ψ, …) up to ``order`` for ``members`` members: what a closed form
        takes, to compile it before the filter's program that gives them has compiled."""
        n = len(spec.free)
        P = (np.zeros(members), np.zeros((members, q)), np.zeros((members, q, q)))
        return np.zeros((members, n)), tuple(tuple(np.zeros(a.shape + (n,) * k) for a in P) for k in range(order + 1))

    members_first = (0, None, 0)

    def kept(name, layout=spec.key()):
        return kept_key(structure, ("population", name, options, layout))

    def on_scales(fun, name):
        """A filter's program of the members' ψ, shared by the layouts of one ``spec.scale_key()``."""
        return jit(jax.vmap(fun, in_axes=members_first), key=kept(name, spec.scale_key()))

    return LaplacePrograms(
        scales=jit(jax.vmap(spec.scale, in_axes=(None, 0, 0, None)), key=kept("scales")),
        likelihood=on_scales(likelihood, "likelihood"),
        on_random=on_scales(on_random, "on random"),
        slopes=on_scales(with_slopes, "slopes"),
        curvatures=on_scales(curvatures, "curvatures"),
        value=jit(jax.vmap(value), key=kept("value")),
        inner=jit(jax.vmap(inner, in_axes=(0, None, 0)), key=kept("inner")),
        gradient=jit(jax.vmap(gradient, in_axes=(None, 0, 0, None, 0, 0, 0)), key=kept("gradient")),
        hessian=jit(jax.vmap(hessian, in_axes=(None, 0, 0, 0, 0, None, 0, 0, 0, 0)), key=kept("hessian")),
        shaped=shaped,
    )


#: Newton decrement gᵀH⁻¹g of the inner problem (log-likelihood units) at which a mode is found.
MODE_TOLERANCE = 1e-12
MODE_MAXITER = 100
#: Decrement (relative to max(1, |g_i|)) below which the inner Newton step is taken without a test.
NEAR = 1e-6


class Modes(NamedTuple):
    u: np.ndarray  # (members, q) conditional modes
    value: np.ndarray  # g_i at the modes
    hessian: np.ndarray  # (members, q, q)
    converged: np.ndarray  # per member
    finite: np.ndarray  # per member: g and its derivatives finite at the mode


def _finite(value, gradient, hessian) -> np.ndarray:
    """Per member: g_i and its derivatives finite."""
    return np.isfinite(value) & np.all(np.isfinite(gradient), axis=1) & np.all(np.isfinite(hessian), axis=(1, 2))


def _newton_steps(gradient, hessian, members) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(steps, decrements, positive)`` of ``members``: Newton steps on the Hessian made positive definite
    by flipping and flooring its eigenvalues, their decrements gᵀH⁻¹g, and where H was positive definite
    already (there the step is the plain Newton step)."""
    steps, decrements = np.zeros_like(gradient), np.zeros(len(gradient))
    positive = np.zeros(len(gradient), dtype=bool)
    for i in members:
        w, V = np.linalg.eigh(0.5 * (hessian[i] + hessian[i].T))
        positive[i] = w.min() > 0
        w = np.maximum(np.abs(w), 1e-8 * max(np.abs(w).max(), 1.0))
        a = V.T @ gradient[i]
        steps[i] = -V @ (a / w)
        decrements[i] = float(np.sum(a ** 2 / w))
    return steps, decrements, positive


def _where(mask, new: tuple, old: tuple) -> tuple:
    """Per member, ``new``'s arrays where ``mask`` holds, ``old``'s elsewhere."""
    return tuple(np.where(mask.reshape((-1,) + (1,) * (b.ndim - 1)), a, b) for a, b in zip(new, old))


def conditional_modes(programs, phi, u0) -> Modes:
    """Each member's û_i = argmin g_i: damped Newton steps on all members at once, each member stopping
    at its own convergence; a non-PD Hessian is made PD by flipping and flooring its eigenvalues.

    ``programs`` has ``inner(u, φ)`` and ``value(u, φ)`` over all members
    ([`MemberPrograms`][greyid.population.laplace.MemberPrograms])."""
    u = np.array(u0, dtype=float)
    value, gradient, hessian = map(np.asarray, programs.inner(u, phi))
    finite = _finite(value, gradient, hessian)
    if not finite.all():  # a start from the previous modes may be far off: from u = 0 instead
        u[~finite] = 0.0
        value, gradient, hessian = map(np.asarray, programs.inner(u, phi))
        finite = _finite(value, gradient, hessian)
    converged = ~finite
    n = len(u)
    for _ in range(MODE_MAXITER):
        step, decrement, _ = _newton_steps(gradient, hessian, np.flatnonzero(~converged))
        converged |= decrement <= MODE_TOLERANCE * np.maximum(1.0, np.abs(value))
        active = ~converged
        if not active.any():
            break
        # Near the mode (decrement below NEAR) a full Newton step is safe and rounding in g_i
        # would fail the decrease test: taken without it.  Elsewhere: backtracking (Armijo).
        previous = u.copy()
        near = active & (decrement <= NEAR * np.maximum(1.0, np.abs(value)))
        u[near] += step[near]
        far = active & ~near
        if far.any():
            scale = np.ones(n)
            accepted = ~far
            trial = u.copy()
            for _ in range(40):
                todo = ~accepted
                trial[todo] = u[todo] + scale[todo, None] * step[todo]
                trial_value = np.asarray(programs.value(trial, phi))
                ok = todo & np.isfinite(trial_value) & (trial_value <= value - 1e-4 * scale * decrement)
                accepted |= ok
                if accepted.all():
                    break
                scale[~accepted] *= 0.5
            converged |= ~accepted  # no decrease even along a tiny step: at the mode to rounding
            u[accepted & far] = trial[accepted & far]
        new = tuple(map(np.asarray, programs.inner(u, phi)))
        fine = _finite(*new)
        u[~fine] = previous[~fine]  # a step into a non-finite region: back, and stop there
        converged |= ~fine
        value, gradient, hessian = _where(fine, new, (value, gradient, hessian))
    # One more full Newton step where H is positive definite: the decrement test above stops at
    # |û error| ~ 1e-6·ω, which quadratic convergence squares away (kept where the value does not
    # rise beyond rounding).
    step, _, positive = _newton_steps(gradient, hessian, np.flatnonzero(_finite(value, gradient, hessian)))
    polished = u + np.where(positive[:, None], step, 0.0)
    new = tuple(map(np.asarray, programs.inner(polished, phi)))
    better = np.isfinite(new[0]) & (new[0] <= value + 1e-12 * np.maximum(1.0, np.abs(value)))
    u[better] = polished[better]
    value, gradient, hessian = _where(better, new, (value, gradient, hessian))
    return Modes(u, value, hessian, converged, _finite(value, gradient, hessian))


def laplace_values(modes: Modes) -> np.ndarray:
    """ℓ_i = g_i(û) + ½ log det H_i(û) per member; inf where H is not positive definite."""
    out = np.full(len(modes.value), np.inf)
    for i, (v, H) in enumerate(zip(modes.value, modes.hessian)):
        if not np.isfinite(v) or not np.all(np.isfinite(H)):
            continue
        w = np.linalg.eigvalsh(0.5 * (H + H.T))
        if w.min() > 0:
            out[i] = v + 0.5 * np.sum(np.log(w))
    return out


#: Members per call of the outer gradient and Hessian programs.  Their chunks run side by side on
#: the cores; small ones keep their many tangents in cache and compile faster
#: (``benchmarks/population.py``).  The inner programs (modes, values), with few tangents, run
#: fastest in one chunk per thread.
DERIVATIVE_MEMBERS = 32

#: With ``hessian="differences"``: the steps, relative to |ψ_j|, of the second differences of a member's
#: likelihood K that find K_jj, whose conditional standard deviations 1/√K_jj scale the central differences of
#: its slopes (``DIFFERENCE_STEP`` of them, as ``optimizer="lbfgs"`` takes its steps), so that they do not depend
#: on the parameters' units.
SCALE_STEP = 1e-3


def next_steps(curvatures, fallback) -> np.ndarray:
    """``DIFFERENCE_STEP``/√K_jj for each member and ψ_j from the members' curvatures K_jj = ∂²K/∂ψ_j² (members ×
    n), ``fallback`` where K_jj is not a positive finite number."""
    scales = conditional_scales(curvatures, np.nan)
    return np.where(np.isnan(scales), fallback, DIFFERENCE_STEP * scales)


def _shifted(psi, h):
    """``(j, ψ + h_j e_j, ψ − h_j e_j)`` for each free parameter's scale j (members along the first axis)."""
    for j in range(psi.shape[1]):
        shift = np.zeros_like(psi)
        shift[:, j] = h[:, j]
        yield j, psi + shift, psi - shift


def _cut(x, data, count: int) -> list[tuple]:
    """The members cut into ``count`` chunks of equal size, the last padded with copies of its first
    member: ``(index, padded index, x, data)`` per chunk, on the device."""
    n = int(np.shape(x)[0])
    size = -(-n // max(1, min(count, n)))
    parts = []
    for start in range(0, n, size):
        index = np.arange(start, min(start + size, n))
        padded = np.concatenate([index, np.full(size - len(index), index[0])])
        # Indexed on the host: a device array's indexing is an operation JAX compiles for each shape.
        chunk = jax.tree_util.tree_map(lambda leaf, padded=padded: jax.device_put(np.asarray(leaf)[padded]), (x, data))
        parts.append((index, padded, *chunk))
    return parts


def _joined(outs: list, parts: list[tuple]):
    """The chunks' results without their padding, joined along the members."""
    pieces = [jax.tree_util.tree_map(lambda leaf, k=len(part[0]): np.asarray(leaf)[:k], out)
              for out, part in zip(outs, parts)]
    return jax.tree_util.tree_map(lambda *leaves: np.concatenate(leaves), *pieces)


def _executables(steps, part) -> list:
    """The executable of each program in ``steps`` (see [`MemberPrograms`][greyid.population.laplace.MemberPrograms]'s
    ``_run``) for the chunk ``part``: a later program's for arrays shaped as the earlier ones' outputs."""
    executables, outs = [], []
    for k, (program, arguments) in enumerate(steps):
        executables.append(program.executable(*arguments(part, outs)))
        if k + 1 < len(steps):
            outs.append(jax.tree_util.tree_map(lambda info: np.zeros(info.shape, info.dtype), executables[-1].out_info))
    return executables


class MemberPrograms:
    """The [`LaplacePrograms`][greyid.population.laplace.LaplacePrograms] bound to the members' data, each call split
    over threads.

    The members are cut into chunks of equal size (the last padded with copies of
    its first member): ``workers`` chunks for the inner programs, chunks of at most
    [`DERIVATIVE_MEMBERS`][greyid.population.laplace.DERIVATIVE_MEMBERS] (at least ``workers``) for the outer
    gradient and Hessian.  One compiled program serves all chunks of a size, and the chunks run side by side
    on the threads: XLA runs one vectorised scan on one core.
    """

    def __init__(self, programs: LaplacePrograms, x, base, data, workers: int):
        from concurrent.futures import ThreadPoolExecutor

        n = int(np.shape(x)[0])
        workers = max(1, min(int(workers), n))
        self.n, self.programs = n, programs
        self.parts = _cut(x, data, workers)
        # At least one chunk per thread: a population of up to DERIVATIVE_MEMBERS would run on one core.
        self.derivative_parts = _cut(x, data, max(workers, -(-n // DERIVATIVE_MEMBERS)))
        self.base = tuple(jax.device_put(np.asarray(b, dtype=float)) for b in base)
        self.pool = ThreadPoolExecutor(len(self.parts))
        self._pending: dict = {}  # programs compiling in the background, by name (see compile_ahead)

    def _run(self, steps, parts=None):
        """Programs run in turn on every chunk, the chunks side by side on the threads.  ``steps``: pairs
        ``(program, arguments(part, outs))``, a program's arguments for a chunk from the chunk and the
        outputs of the programs before it.  The executables are fetched first, here, for the first chunk
        (the chunks are of one size; a later program's for the shapes of the earlier ones' outputs):
        compiled or loaded once, where threads started together would each trace and compile them, and
        then every chunk runs at once, on the first call as on later ones."""
        parts = self.parts if parts is None else parts
        executables = _executables(steps, parts[0])

        def run(part):
            outs = []
            for (program, arguments), executable in zip(steps, executables):
                outs.append(executable(*program.dynamic(arguments(part, outs))))
            return jax.device_get(outs[-1])

        return _joined(list(self.pool.map(run, parts)), parts)

    def _at_scales(self, phi, u, on_scales, closed_form) -> list:
        """ψ at the random effects ``u``, the filter's program ``on_scales`` there, then ``closed_form(part,
        outs)`` (see `_run`)."""
        programs, base = self.programs, self.base
        return [(programs.scales, lambda part, _: (phi, u[part[1]], part[2], base)),
                (on_scales, lambda part, outs: (outs[0], base, part[3])), closed_form]

    def value(self, u, phi):
        """g_i per member at the random effects ``u``."""
        phi, u = jnp.asarray(phi), np.asarray(u)
        return self._run(self._at_scales(phi, u, self.programs.likelihood,
                                         (self.programs.value, lambda part, outs: (u[part[1]], outs[1]))))

    def inner(self, u, phi):
        """``(g_i, ∇_u g_i, ∇²_u g_i)`` per member at the random effects ``u``."""
        phi, u = jnp.asarray(phi), np.asarray(u)
        return self._run(self._at_scales(phi, u, self.programs.on_random,
                                         (self.programs.inner, lambda part, outs: (u[part[1]], phi, outs[1]))))

    def _gradient_steps(self, phi, u) -> list:
        """ψ at the modes ``u``, P and its slopes there, then ℓ_i, ℓ_i', T_i and λ_i (see `_run`)."""
        base = self.base
        return self._at_scales(phi, u, self.programs.slopes, (
            self.programs.gradient, lambda part, outs: (phi, u[part[1]], part[2], base, outs[0], *outs[1])))

    def _hessian_steps(self, phi, u, tangents, multipliers) -> list:
        """ψ at the modes ``u``, P and its first and second derivatives there, then ℓ_i'' (see `_run`)."""
        base = self.base
        return self._at_scales(phi, u, self.programs.curvatures, (
            self.programs.hessian, lambda part, outs: (phi, u[part[1]], tangents[part[1]], multipliers[part[1]],
                                                       part[2], base, outs[0], *outs[1])))

    def gradient(self, phi, u):
        """``(ℓ_i, ℓ_i', T_i, λ_i)`` per member at the modes ``u``; T and λ are what ``hessian`` takes."""
        steps = self._gradient_steps(jnp.asarray(phi), np.asarray(u))
        self._compiled_ahead("gradient", steps, 1)
        return self._run(steps, self.derivative_parts)

    def compile_ahead(self, phi, u, hessian: bool = False) -> None:
        """Compile the filter's programs of the outer gradient (and with ``hessian`` those of the exact Hessian
        after them) in the background, the arguments giving only their shapes: the largest programs, needed
        after the members' modes (the Hessian's last), so their compilation overlaps the modes' programs and the
        search instead of following them."""
        from concurrent.futures import ThreadPoolExecutor

        n, p, q = len(u), len(phi), np.shape(u)[1]
        phi, u, part = jnp.asarray(phi), np.asarray(u), self.derivative_parts[0]
        compiler = ThreadPoolExecutor(1)
        self._pending["gradient"] = compiler.submit(_executables, self._gradient_steps(phi, u)[:-1], part)
        if hessian:
            steps = self._hessian_steps(phi, u, np.zeros((n, q + p, p)), np.zeros((n, q)))
            self._pending["hessian"] = compiler.submit(_executables, steps[:-1], part)
        compiler.shutdown(wait=False)

    def _compiled_ahead(self, name: str, steps, order: int) -> None:
        """Wait for the filter's programs of ``name`` compiling in the background (`compile_ahead`), where they
        are, compiling the closed form ``steps[-1]`` meanwhile (for P's derivatives up to ``order``)."""
        pending = self._pending.pop(name, None)
        if pending is not None:
            part = self.derivative_parts[0]
            closed_form, arguments = steps[-1]
            closed_form.executable(*arguments(part, self.programs.shaped(len(part[1]), order)))
            pending.result()  # (an error there is raised here)

    def hessian(self, phi, u, tangents, multipliers):
        """ℓ_i'' per member, from the modes ``u`` and the ``tangents`` T and ``multipliers`` λ that ``gradient``
        gave at the same φ; in chunks of [`DERIVATIVE_MEMBERS`][greyid.population.laplace.DERIVATIVE_MEMBERS], split
        over the threads as the gradient's."""
        steps = self._hessian_steps(jnp.asarray(phi), np.asarray(u), np.asarray(tangents), np.asarray(multipliers))
        self._compiled_ahead("hessian", steps, 2)
        return self._run(steps, self.derivative_parts)

    def _curvatures_by_differences(self, phi, u, steps, part) -> tuple:
        """For one chunk: ψ at the modes ``u``, P and its slopes there, and P's second derivatives in ψ by central
        differences of the slopes at ψ ± ``steps[i, j]``·e_j, symmetrised ([..., k, j] = ∂²P/∂ψ_k∂ψ_j)."""
        base, slopes = self.base, self.programs.slopes
        psi = np.asarray(self.programs.scales(phi, u[part[1]], part[2], base), dtype=float)
        P0, P1 = jax.device_get(slopes(psi, base, part[3]))
        h = steps[part[1]]
        columns = []
        for j, up, down in _shifted(psi, h):
            ahead = jax.device_get(slopes(up, base, part[3])[1])
            behind = jax.device_get(slopes(down, base, part[3])[1])
            columns.append([(np.asarray(a) - np.asarray(b)) / (2 * h[:, j]).reshape((-1,) + (1,) * (np.ndim(a) - 1))
                            for a, b in zip(ahead, behind)])
        P2 = tuple(np.stack([column[k] for column in columns], axis=-1) for k in range(len(P0)))
        return psi, P0, P1, tuple(0.5 * (a + np.swapaxes(a, -1, -2)) for a in P2)

    def _curvature_diagonal(self, phi, u, part) -> tuple:
        """For one chunk of the inner programs' (which have compiled): each member's ∂²K/∂ψ_j² by second
        differences of K (the ``on_random`` program's first output) at ψ ± h_j e_j, h_j = ``SCALE_STEP``·|ψ_j|
        (``SCALE_STEP`` where ψ_j = 0), and those h."""
        base, on_random = self.base, self.programs.on_random
        psi = np.asarray(self.programs.scales(phi, u[part[1]], part[2], base), dtype=float)
        h = SCALE_STEP * np.where(psi != 0.0, np.abs(psi), 1.0)
        centre = np.asarray(on_random(psi, base, part[3])[0])
        curvatures = np.empty_like(psi)
        for j, up, down in _shifted(psi, h):
            ahead, behind = (np.asarray(on_random(at, base, part[3])[0]) for at in (up, down))
            curvatures[:, j] = (ahead - 2.0 * centre + behind) / h[:, j] ** 2
        return curvatures, h

    def hessian_by_differences(self, phi, u, tangents, multipliers, steps):
        """ℓ_i'' per member as `hessian` gives it, with P's second derivatives in ψ by central differences of
        its exact first derivatives (the gradient's own ``slopes`` program: no program of the filter's to
        compile), along ψ_j a step ``steps[i, j]`` for member i.  Where a member's steps are not all positive
        numbers, second differences of K by the inner programs give each member's curvatures along ψ_j first
        (`_curvature_diagonal`).  Returns ``(ℓ_i'', steps for a later call)``: ``DIFFERENCE_STEP`` conditional
        standard deviations of each member's K along each ψ_j
        ([`next_steps()`][greyid.population.laplace.next_steps]), the steps used where those are not positive."""
        phi, u = jnp.asarray(phi), np.asarray(u)
        tangents, multipliers = np.asarray(tangents), np.asarray(multipliers)
        steps = np.array(steps, dtype=float)
        unknown = ~np.all(np.isfinite(steps) & (steps > 0), axis=1)
        parts = self.derivative_parts
        if unknown.any():
            curvatures, guess = _joined(list(self.pool.map(lambda part: self._curvature_diagonal(phi, u, part),
                                                           self.parts)), self.parts)
            steps[unknown] = next_steps(curvatures, guess)[unknown]
        closed_form = self.programs.hessian
        part = parts[0]
        psi, P = self.programs.shaped(len(part[1]), 2)
        # Compiled (or loaded) once here, not by each thread at once.
        closed_form.executable(phi, u[part[1]], tangents[part[1]], multipliers[part[1]], part[2], self.base, psi, *P)

        def run(part):
            psi, P0, P1, P2 = self._curvatures_by_differences(phi, u, steps, part)
            return jax.device_get(closed_form(phi, u[part[1]], tangents[part[1]], multipliers[part[1]], part[2],
                                              self.base, psi, P0, P1, P2)), (P2[0],)

        hessians, (curvatures,) = _joined(list(self.pool.map(run, parts)), parts)
        return np.asarray(hessians), next_steps(np.diagonal(curvatures, axis1=-2, axis2=-1), steps)

    def close(self):
        self.pool.shutdown()
