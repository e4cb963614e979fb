"""A two-state RC model of a building (indoor air Ti, envelope Tw) and its bundled data.

Units: time in hours, temperatures in °C, heat in kW, solar irradiance in kW/m²,
capacities in kWh/K, resistances in K/kW.  The data in ``building.csv`` were
simulated from this model at :data:`TRUE_PARAMETERS` by
``scripts/make_bundled_data.py`` (one week at 10-minute sampling, PRBS heating).
"""

from __future__ import annotations

from importlib import resources

import pandas as pd

from ..model import Model

#: Parameter values the bundled data were simulated with.
TRUE_PARAMETERS = {
    "Ci": 2.0, "Cw": 20.0, "Riw": 1.0, "Rwe": 10.0, "Aw": 5.0,
    "p11": -3.0, "p22": -4.0, "e11": -4.6, "Ti0": 20.0, "Tw0": 12.0,
}


def building_model() -> Model:
    """The two-state model dTi, dTw with inputs Te, Gv, Qi and output yTi."""
    m = Model("TiTw")
    m.add_system("dTi = (1/(Ci*Riw)*(Tw-Ti) + Aw/Ci*Gv + Qi/Ci)*dt + exp(p11)*dw1")
    m.add_system("dTw = (1/(Cw*Riw)*(Ti-Tw) + 1/(Cw*Rwe)*(Te-Tw))*dt + exp(p22)*dw2")
    m.add_inputs("Te", "Gv", "Qi")
    m.add_observation("yTi = Ti", variance="exp(e11)")
    m.set_initial_state(mean={"Ti": "Ti0", "Tw": "Tw0"}, covariance="process", scale=1.0)
    bounds = {  # (initial value, lower, upper): starting values a physicist would guess
        "Ci": (1.0, 0.01, 100.0), "Cw": (10.0, 0.1, 1000.0), "Riw": (0.5, 0.01, 100.0),
        "Rwe": (5.0, 0.1, 1000.0), "Aw": (3.0, 0.0, 50.0), "p11": (-2.0, -20.0, 5.0),
        "p22": (-2.0, -20.0, 5.0), "e11": (-3.0, -20.0, 5.0), "Ti0": (20.0, 0.0, 40.0), "Tw0": (15.0, -10.0, 40.0),
    }
    for name, (init, lower, upper) in bounds.items():
        m.set_parameter(name, init=init, lower=lower, upper=upper)
    return m


def load_building_data() -> pd.DataFrame:
    """The bundled simulated data: columns t [h], Te, Gv, Qi, yTi."""
    with resources.files(__package__).joinpath("building.csv").open("r") as fh:
        return pd.read_csv(fh)
