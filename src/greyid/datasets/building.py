"""A two-state RC model of a building (indoor air Ti, envelope Tw) and its bundled data.

Units: time in hours, temperatures in °C, heat in kW, solar irradiance in kW/m²,
capacities in kWh/K, resistances in K/kW.  The data in ``building.csv`` were
simulated from this model at [`TRUE_PARAMETERS`][greyid.datasets.building.TRUE_PARAMETERS] by
``scripts/make_bundled_data.py`` (one week at 10-minute sampling, PRBS heating).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pandas as pd

from ..api import Model

#: Parameter values the bundled data were simulated with.
TRUE_PARAMETERS = {
    "Ci": 2.0, "Cw": 20.0, "Riw": 1.0, "Rwe": 10.0, "Aw": 5.0,
    "p11": -3.0, "p22": -4.0, "e11": -4.6, "Ti0": 20.0, "Tw0": 12.0,
}


def building_model() -> Model:
    """The two-state model dTi, dTw with inputs Te, Gv, Qi and output yTi (``building.toml``)."""
    return Model.from_toml(model_file())


def model_file() -> Path:
    """Path of the bundled model file (its ``[data] file`` is the bundled CSV)."""
    return Path(str(resources.files(__package__).joinpath("building.toml")))


def load_building_data() -> pd.DataFrame:
    """The bundled simulated data: columns t [h], Te, Gv, Qi, yTi."""
    with resources.files(__package__).joinpath("building.csv").open("r") as fh:
        return pd.read_csv(fh)
