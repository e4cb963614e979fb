"""The likelihood's cost per call, beside a plain JAX scan of the same filter (issue "public likelihood").

    python benchmarks/likelihood.py [--rounds 10] [--calls 100] [--source OTHER_CHECKOUT/src] [--first]

The Armadillo model (pySIP's TwTi_RoRi, first-order hold, 232 rows, seven free
parameters; the data set armadillo) at its fitted
optimum and at its starting values:

* greyid: ``model.likelihood(data).value_and_grad(x)``, the public call with
  NumPy in and out, and ``.value``, ``.hessian``;
* the plain scan it is compared with: the same filter written as one
  ``jax.lax.scan`` over the rows — Φ, Γ, Υ and Λ from ``jax.scipy.linalg.expm``
  of Van Loan's block matrices once per call, the plain covariance update,
  first-order hold — under ``jax.jit(jax.value_and_grad(...))`` (reverse mode)
  with JAX's default compiler options;
* the warm fit: ``model.fit`` again in the same process (median and fastest of 15).

The calls take turns in ``--rounds`` rounds of ``--calls`` calls each; a
figure is the fastest call of all.  The machine's speed drifts by 10–30 %
between minutes, and more on a shared one, so the ratio to the plain scan is
also taken round by round (the fastest call of each in the same round): its
median and range are printed beside the ratio of the fastest calls.  The
values and gradients of both are checked against each other first.
``--source`` runs another checkout's greyid in the same way (the figures before
a change), its own plain scan beside it.  ``--first`` prints instead the first
call of ``value_and_grad`` and then of ``hessian`` at the starting values in this
process (run it twice with one ``GREYID_CACHE_DIR``: the first run with an empty
folder, the second loading what the first kept).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import durations, fastest  # noqa: E402



def plain_scan(data, names):
    """The plain JAX scan of the Armadillo filter: (θ in ``names``' order) ↦ negative log-likelihood."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.scipy.linalg import expm

    t = data["Time"].to_numpy()
    inputs = jnp.asarray(np.stack([data["T_ext"].to_numpy(), data["P_hea"].to_numpy()], axis=1))
    y = jnp.asarray(data["T_int"].to_numpy())
    dt = float(t[1] - t[0])
    assert np.allclose(np.diff(t), dt), "the plain scan assumes a regular series"

    def negative_loglik(theta):
        p = dict(zip(names, theta))
        Ro, Ri, Cw, Ci, sigw, sigv, Tw0 = (p[k] for k in ("Ro", "Ri", "Cw", "Ci", "sigw", "sigv", "Tw0"))
        A = jnp.array([[-1 / (Cw * Ro) - 1 / (Cw * Ri), 1 / (Cw * Ri)], [1 / (Ci * Ri), -1 / (Ci * Ri)]])
        B = jnp.array([[1 / (Cw * Ro), 0.0], [0.0, 1 / Ci]])
        Q = jnp.array([[sigw**2, 0.0], [0.0, 0.0]])
        E = expm(jnp.block([[-A, Q], [jnp.zeros((2, 2)), A.T]]) * dt)  # Van Loan: Φ and Λ
        Phi = E[2:, 2:].T
        Lam = Phi @ E[:2, 2:]
        M = jnp.zeros((6, 6)).at[:2, :2].set(A).at[:2, 2:4].set(B).at[2:4, 4:6].set(jnp.eye(2) / dt)
        G = expm(M * dt)  # the held and the ramped inputs' gains
        Gam, Ups = G[:2, 2:4], G[:2, 4:6]
        S = sigv**2

        def update(x, P, yk):  # y = Ti: C = (0, 1)
            e = yk - x[1]
            R = P[1, 1] + S
            K = P[:, 1] / R
            return x + K * e, P - jnp.outer(K, P[1, :]), 0.5 * (jnp.log(R) + e * e / R + jnp.log(2 * jnp.pi))

        x, P, first = update(jnp.array([Tw0, 26.7]), 0.01 * jnp.eye(2), y[0])

        def step(carry, row):
            x, P, total = carry
            u_prev, u_cur, yk = row
            x, P, term = update(Phi @ x + Gam @ u_prev + Ups @ (u_cur - u_prev), Phi @ P @ Phi.T + Lam, yk)
            return (x, P, total + term), None

        (_, _, total), _ = jax.lax.scan(step, (x, P, first), (inputs[:-1], inputs[1:], y[1:]))
        return total

    return negative_loglik


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--calls", type=int, default=100, help="calls of each function per round")
    parser.add_argument("--source", help="another checkout's src folder, measured instead of this one's")
    parser.add_argument("--first", action="store_true", help="time the first calls in this process only")
    args = parser.parse_args(argv)
    if args.source:
        sys.path.insert(0, str(Path(args.source).resolve()))
    warnings.simplefilter("ignore")
    import jax
    import numpy as np

    import greyid
    from greyid.datasets.reference import armadillo_model

    print(f"greyid from {Path(greyid.__file__).parent}, JAX {jax.__version__}")
    data = greyid.datasets.fetch("armadillo").iloc[:-1]
    model = armadillo_model()
    if args.first:
        nll = model.likelihood(data, time="Time", hold="foh")
        for name in ("value_and_grad", "hessian"):
            start = time.perf_counter()
            getattr(nll, name)(nll.start())
            print(f"first {name}: {time.perf_counter() - start:.2f} s")
        return
    fit = model.fit(data, time="Time", hold="foh")
    nll = model.likelihood(data, time="Time", hold="foh")
    optimum = np.array([fit.values[n] for n in nll.names])
    plain = jax.jit(jax.value_and_grad(plain_scan(data, nll.names)))
    for label, x in (("optimum", optimum), ("starting values", nll.start())):
        value, gradient = nll.value_and_grad(x)
        plain_value, plain_gradient = (np.asarray(a) for a in plain(x))
        scale = np.max(np.abs(plain_gradient * x))
        print(f"at the {label}: value {value:.10f} (plain scan {plain_value:.10f}, difference "
              f"{abs(value - plain_value):.1e}); gradient × |x| differs by "
              f"{np.max(np.abs((gradient - plain_gradient) * x)) / scale:.1e} of its largest element")
    rows = len(data)
    calls = {"value and gradient": lambda: nll.value_and_grad(optimum),
             "plain scan, value and gradient": lambda: jax.block_until_ready(plain(optimum)),
             "value": lambda: nll.value(optimum),
             "value and gradient at the starting values": lambda: nll.value_and_grad(nll.start()),
             "Hessian": lambda: nll.hessian(optimum)}
    rounds = [{name: fastest(call, args.calls) for name, call in calls.items()} for _ in range(args.rounds)]
    for name in calls:
        seconds = min(r[name] for r in rounds)
        print(f"  {name}: {seconds * 1e3:.3f} ms per call ({seconds * 1e6 / rows:.2f} µs per row)")
    vg, scan = "value and gradient", "plain scan, value and gradient"
    each = sorted(r[vg] / r[scan] for r in rounds)
    print(f"  value and gradient / plain scan: {min(r[vg] for r in rounds) / min(r[scan] for r in rounds):.2f} "
          f"(round by round: median {np.median(each):.2f}, range {each[0]:.2f}–{each[-1]:.2f})")
    fits, again = durations(lambda: model.fit(data, time="Time", hold="foh"), 15)
    print(f"  warm fit: median {np.median(fits) * 1e3:.1f} ms, fastest {min(fits) * 1e3:.1f} ms "
          f"(log L {again.loglik:.6f}, {again.iterations} iterations)")


if __name__ == "__main__":
    main()
