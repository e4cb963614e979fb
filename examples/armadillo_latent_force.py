"""The Armadillo box with a latent heat gain: pySIP's TwTi_RoRi model alone, with a Matérn-3/2 force and with a
quasi-periodic (daily) force; fit, information criteria, residual tests, and the smoothed force beside the
measured solar irradiance that none of the models uses.

Run from the repository root:  python examples/armadillo_latent_force.py [OUT_DIR]   (default out/latent_force)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import greyid  # noqa: E402
from greyid import library  # noqa: E402

MODELS = {"no force": lambda: greyid.Model.from_toml(Path(__file__).with_name("armadillo.toml")),
          "Matérn-3/2 force": lambda: library.load_model("armadillo_matern32"),
          "quasi-periodic force": lambda: library.load_model("armadillo_quasiperiodic")}


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/latent_force")
    out.mkdir(parents=True, exist_ok=True)
    data = greyid.datasets.fetch("armadillo")
    print(f"{'model':22s} {'states':>6s} {'params':>6s} {'loglik':>9s} {'AIC':>9s} {'BIC':>9s} "
          f"{'tests rejecting':>15s} {'first fit [s]':>13s} {'again [s]':>9s}")
    fits = {}
    for name, make in MODELS.items():
        model = make()
        start = time.perf_counter()
        fit = model.fit(data)
        first = time.perf_counter() - start
        start = time.perf_counter()
        fit = model.fit(data)
        again = time.perf_counter() - start
        validation = fit.validate()
        rejecting = int(validation.tests["reject"].sum())
        fits[name] = fit
        print(", ".join(validation.rejected["test"] + " " + validation.rejected["output"]) or "none rejects")
        print(f"{name:22s} {len(model.state_names):6d} {fit.n_params:6d} {fit.loglik:9.2f} {fit.aic:9.2f} "
              f"{fit.bic:9.2f} {rejecting:>8d} of {len(validation.tests):<4d} {first:13.1f} {again:9.2f}")
    print()
    hours = data["Time"].to_numpy() / 3600
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for name in ("Matérn-3/2 force", "quasi-periodic force"):
        force = fits[name].smooth().latent_forces
        correlation = np.corrcoef(force["Q"], data["I_sol"])[0, 1]
        print(f"{name}: smoothed Q against the measured solar irradiance I_sol (not in the model): "
              f"correlation {correlation:.2f}; Q from {force['Q'].min():.0f} to {force['Q'].max():.0f} W, "
              f"mean standard deviation {force['Q_sd'].mean():.0f} W")
        ax.plot(hours, force["Q"], label=f"Q, {name}")
        ax.fill_between(hours, force["Q"] - 2 * force["Q_sd"], force["Q"] + 2 * force["Q_sd"], alpha=0.2)
    ax2 = ax.twinx()
    ax2.plot(hours, data["I_sol"], color="0.5", lw=0.8, label="I_sol (measured, unused)")
    ax.set_xlabel("time [h]")
    ax.set_ylabel("latent heat gain Q [W]")
    ax2.set_ylabel("solar irradiance [W/m²]")
    ax.legend(loc="upper left", fontsize=8)
    ax2.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "armadillo_latent_force.png", dpi=110)
    print(f"wrote {out / 'armadillo_latent_force.png'}")


if __name__ == "__main__":
    main()
