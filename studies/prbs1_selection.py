"""Forward model selection on the PRBS1 test house (Bacher & Madsen, 2011).

Start from the one-state model Ti and, at each step, try every extension by one
more state — envelope Te, heater Th, sensor Ts, interior medium Tm — keep the
one with the highest likelihood, and stop when the likelihood-ratio test no
longer rejects at 5 %.  Data: ../shared/data/prbs1_test_house/inputPRBS1.csv
(read from there, not copied).  Run: python studies/prbs1_selection.py
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pandas as pd

import greyid
from greyid import validation

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "prbs1_test_house" / "inputPRBS1.csv"
PARTS = ("e", "h", "s", "m")  # envelope, heater, sensor, medium
NAMES = {"e": "Te", "h": "Th", "s": "Ts", "m": "Tm"}


def rc_model(parts: frozenset) -> greyid.Model:
    """The RC network with Ti and the states named by ``parts`` (Bacher & Madsen's family)."""
    name = "Ti" + "".join(NAMES[p] for p in PARTS if p in parts)
    m = greyid.Model(name)
    flows = ["(Te-Ti)/(Rie*Ci)" if "e" in parts else "(Ta-Ti)/(Ria*Ci)", "Aw/Ci*Ps"]
    flows.append("(Th-Ti)/(Rih*Ci)" if "h" in parts else "Ph/Ci")
    if "m" in parts:
        flows.append("(Tm-Ti)/(Rim*Ci)")
    m.add_system(f"dTi = ({' + '.join(flows)})*dt + exp(pTi)*dw1")
    bounds = {"Ci": (0.1, 1e-3, 50), "Aw": (1.0, -5, 50), "pTi": (-2, -20, 5), "Ti0": (21, 10, 35)}
    if "e" in parts:
        m.add_system("dTe = ((Ti-Te)/(Rie*Ce) + (Ta-Te)/(Rea*Ce))*dt + exp(pTe)*dw2")
        bounds.update(Rie=(1.0, 1e-3, 100), Rea=(4.0, 1e-3, 100), Ce=(2.0, 1e-3, 100), pTe=(-2, -20, 5),
                      Te0=(15, -10, 35))
    else:
        bounds.update(Ria=(5.0, 1e-3, 100))
    if "h" in parts:
        m.add_system("dTh = ((Ti-Th)/(Rih*Ch) + Ph/Ch)*dt + exp(pTh)*dw3")
        bounds.update(Rih=(0.5, 1e-3, 100), Ch=(0.05, 1e-4, 10), pTh=(-2, -20, 5), Th0=(25, 10, 60))
    if "m" in parts:
        m.add_system("dTm = ((Ti-Tm)/(Rim*Cm))*dt + exp(pTm)*dw4")
        bounds.update(Rim=(0.5, 1e-3, 100), Cm=(1.0, 1e-3, 100), pTm=(-2, -20, 5), Tm0=(21, 10, 35))
    if "s" in parts:
        m.add_system("dTs = ((Ti-Ts)/(Ris*Cs))*dt + exp(pTs)*dw5")
        bounds.update(Ris=(0.5, 1e-3, 100), Cs=(0.05, 1e-4, 10), pTs=(-2, -20, 5), Ts0=(21, 10, 35))
        m.add_observation("yTi = Ts", variance="exp(e11)")
    else:
        m.add_observation("yTi = Ti", variance="exp(e11)")
    bounds["e11"] = (-6, -25, 5)
    m.add_inputs("Ta", "Ps", "Ph")
    states = ["Ti"] + [NAMES[p] for p in ("e", "h", "m", "s") if p in parts]
    m.set_initial_state(mean={s: f"{s}0" for s in states},
                        covariance=[[0.01 if i == j else 0.0 for j in states] for i in states])
    for p, (init, lo, hi) in bounds.items():
        m.set_parameter(p, init=init, lower=lo, upper=hi)
    return m


def extensions(current: greyid.Model) -> list[greyid.Model]:
    have = frozenset(p for p in PARTS if NAMES[p] in current.state_names)
    return [rc_model(have | {p}) for p in PARTS if p not in have]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", type=float, default=0.05)
    parser.add_argument("--starts", type=int, default=3)
    args = parser.parse_args(argv)
    data = pd.read_csv(DATA, sep=";")
    started = time.perf_counter()
    result = validation.select_forward([rc_model(frozenset()), extensions, extensions, extensions, extensions],
                                       data, level=args.level, starts=args.starts)
    with pd.option_context("display.width", 140):
        print(result.table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    chosen = result.chosen
    print(f"\nchosen: {chosen.model.name}  ({time.perf_counter() - started:.0f} s)\n")
    print(chosen.summary())
    print(chosen.validate().summary())


if __name__ == "__main__":
    main()
