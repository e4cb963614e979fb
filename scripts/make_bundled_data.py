"""Regenerate src/greyid/datasets/building.csv (deterministic, seeded)."""

from pathlib import Path

import numpy as np
import pandas as pd

from greyid.datasets import TRUE_PARAMETERS, building_model
from greyid.simulate import prbs


def main() -> None:
    rng = np.random.default_rng(2026)
    t = np.arange(7 * 24 * 6) / 6.0  # one week, 10-minute sampling, hours
    day = 2 * np.pi * t / 24.0
    te = 5.0 + 3.0 * np.sin(day - 2.0) + np.cumsum(rng.normal(0, 0.05, len(t)))
    gv = np.clip(0.5 * np.sin(day - np.pi / 2 + 0.3), 0.0, None) * (0.6 + 0.4 * rng.random(len(t)))
    qi = prbs(6, clock=6, levels=(0.0, 2.0), length=len(t))
    inputs = pd.DataFrame({"t": t, "Te": te.round(3), "Gv": gv.round(4), "Qi": qi})
    sim = building_model().simulate(TRUE_PARAMETERS, inputs, n_paths=1, method="exact", seed=7)
    data = inputs.assign(yTi=sim.outputs[0, :, 0].round(4))
    out = Path(__file__).resolve().parents[1] / "src" / "greyid" / "datasets" / "building.csv"
    data.to_csv(out, index=False)
    print(f"wrote {len(data)} rows to {out}")


if __name__ == "__main__":
    main()
