"""Ready models: RC networks of building physics and the thesis' examples.

    from greyid import library
    library.available()                 # names and one-line descriptions
    m = library.load_model("TiTe")      # a Model, ready to fit
    print(m.to_toml())                  # its model file, to copy and edit

The building models are the RC family of Bacher & Madsen (2011), built by
[`rc_network()`][greyid.library.rc_network] from the indoor air state Ti and any of the envelope Te,
heater Th, interior medium Tm and sensor Ts states, with inputs Ta (ambient
temperature, °C), Ps (solar irradiance, kW/m²) and Ph (heating power, kW) and
output yTi; time in hours, C in kWh/K, R in K/kW.  The others are model files
in ``library/models``: the test cell (7.43), the fuel film (8.1–8.3), logistic
growth (2.30) and Lotka–Volterra (A.66).  ``wallN`` is a homogeneous wall of N
nodes (`walls`, section 7.1), with the exact and lumped frequency responses.
"""

from __future__ import annotations

from importlib import resources
from typing import Iterable

from ..errors import ModelError
from ..api import Model
from .walls import ladder_polynomials, lumped_wall, wall_frequency_response, wall_model

#: Extra states of the RC family, in the order they appear in a model's name.
RC_STATES = ("Te", "Th", "Tm", "Ts")
_RC_WHAT = {"Te": "envelope", "Th": "heater", "Tm": "interior medium", "Ts": "sensor"}
#: The building models listed by [`names()`][greyid.library.names]; any other combination of the RC
#: states loads too, in any order (``TiThTeTs`` is ``TiTeThTs``).
BUILDING_MODELS = ("Ti", "TiTe", "TiTh", "TiTm", "TiTeTh", "TiTeThTs", "TiTeThTmTs")


def _rc_states(name: str) -> tuple[str, ...] | None:
    """The extra states named by e.g. ``"TiThTe"``, or ``None`` if it is no RC name."""
    if not name.startswith("Ti") or len(name) % 2:
        return None
    parts = tuple(name[i:i + 2] for i in range(2, len(name), 2))
    if any(p not in RC_STATES for p in parts) or len(set(parts)) != len(parts):
        return None
    return parts


def rc_network(states: Iterable[str] = ()) -> Model:
    """The RC building model with Ti and the extra ``states``.

    Ti exchanges heat with the ambient through Ria, or with the envelope Te
    through Rie (Te then with the ambient through Rea); the heating power enters
    Ti, or the heater Th (through Rih); the medium Tm exchanges with Ti through
    Rim; the sensor Ts follows Ti through Ris·Cs and is what yTi measures.  Solar
    gains enter Ti through the effective window area Aw.  Inputs Ta [°C], Ps
    [kW/m²], Ph [kW]; time in hours.

    Parameters
    ----------
    states : iterable of str
        Any of ``"Te"``, ``"Th"``, ``"Tm"``, ``"Ts"``.

    Returns
    -------
    Model
        The model, named by its states (``"TiTeTh"``), with its nested-start rule.

    Raises
    ------
    ModelError
        An unknown or repeated state.
    """
    extra = tuple(states)
    unknown = [s for s in extra if s not in RC_STATES]
    if unknown or len(set(extra)) != len(extra):
        raise ModelError(f"RC states must be distinct names from {list(RC_STATES)}, got {list(extra)}")
    extra = tuple(s for s in RC_STATES if s in extra)
    name = "Ti" + "".join(extra)
    what = ", ".join(["indoor air Ti"] + [f"{_RC_WHAT[s]} {s}" for s in extra])
    m = Model(name, f"RC building model with {what}. Inputs Ta [degC], Ps [kW/m2], Ph [kW]; "
                    "time in hours, C in kWh/K, R in K/kW.")
    flows = ["(Te - Ti)/(Rie*Ci)" if "Te" in extra else "(Ta - Ti)/(Ria*Ci)", "Aw/Ci*Ps"]
    flows.append("(Th - Ti)/(Rih*Ci)" if "Th" in extra else "Ph/Ci")
    if "Tm" in extra:
        flows.append("(Tm - Ti)/(Rim*Ci)")
    m.add_system(f"dTi = ({' + '.join(flows)})*dt + exp(pTi)*dw1")
    bounds = {"Ci": (0.1, 1e-3, 50), "Aw": (1.0, 0, 50), "pTi": (-2, -20, 5), "Ti0": (21, 10, 35)}
    if "Te" in extra:
        m.add_system("dTe = ((Ti - Te)/(Rie*Ce) + (Ta - Te)/(Rea*Ce))*dt + exp(pTe)*dw2")
        bounds.update(Rie=(1.0, 1e-3, 100), Rea=(4.0, 1e-3, 100), Ce=(2.0, 1e-3, 100), pTe=(-2, -20, 5),
                      Te0=(15, -10, 35))
        m.add_derived("UA [kW/K]", "1/(Rie + Rea)")
    else:
        bounds.update(Ria=(5.0, 1e-3, 100))
        m.add_derived("UA [kW/K]", "1/Ria")
    if "Th" in extra:
        m.add_system("dTh = ((Ti - Th)/(Rih*Ch) + Ph/Ch)*dt + exp(pTh)*dw3")
        bounds.update(Rih=(0.5, 1e-3, 100), Ch=(0.05, 1e-4, 10), pTh=(-2, -20, 5), Th0=(25, 10, 60))
    if "Tm" in extra:
        m.add_system("dTm = ((Ti - Tm)/(Rim*Cm))*dt + exp(pTm)*dw4")
        bounds.update(Rim=(0.5, 1e-3, 100), Cm=(1.0, 1e-3, 100), pTm=(-2, -20, 5), Tm0=(21, 10, 35))
    if "Ts" in extra:
        m.add_system("dTs = ((Ti - Ts)/(Ris*Cs))*dt + exp(pTs)*dw5")
        bounds.update(Ris=(0.5, 1e-3, 100), Cs=(0.05, 1e-4, 10), pTs=(-2, -20, 5), Ts0=(21, 10, 35))
    m.add_observation("yTi = Ts" if "Ts" in extra else "yTi = Ti", variance="exp(e11)")
    bounds["e11"] = (-6, -25, 5)
    m.add_inputs("Ta", "Ps", "Ph")
    all_states = ["Ti", *extra]
    m.set_initial_state(mean={s: f"{s}0" for s in all_states},
                        covariance=[[0.01 if i == j else 0.0 for j in all_states] for i in all_states])
    for p, (init, lo, hi) in bounds.items():
        m.set_parameter(p, init=init, lower=lo, upper=hi)
    capacities = [c for s, c in (("Ti", "Ci"), ("Te", "Ce"), ("Th", "Ch"), ("Tm", "Cm"), ("Ts", "Cs"))
                  if s in all_states]
    m.add_derived("C_total [kWh/K]", " + ".join(capacities))
    m.set_options(time="t", hold="zoh")
    m.set_units(_rc_units(all_states, bounds))
    m.set_nested_start(lambda values: _nested_rc_start(extra, values))
    return m


def _rc_units(states, parameters) -> dict[str, str]:
    """Units of an RC model: hours, °C, kW, kW/m², kWh/K, K/kW, m²; noise intensities in K/√h."""
    units = {"t": "h", "Ta": "degC", "Ps": "kW/m^2", "Ph": "kW", "yTi": "degC", "Aw": "m^2", "e11": "K^2"}
    units.update({s: "degC" for s in states})
    for name in parameters:
        if name.endswith("0"):
            units[name] = "degC"
        elif name.startswith("C"):
            units[name] = "kWh/K"
        elif name.startswith("R"):
            units[name] = "K/kW"
        elif name.startswith("p"):
            units[name] = "K/h^0.5"
    return units


def _nested_rc_start(extra: tuple[str, ...], values: dict) -> dict:
    """Start values where the RC model with ``extra`` states reduces to a smaller one (``values``).

    A state the smaller model lacks starts where it vanishes: a sensor or heater
    with a time constant of 1e-5 h (Ris·Cs, Rih·Ch) follows Ti; an envelope with a
    small capacity splits Ria into Rie + Rea; a medium behind a large Rim is
    decoupled; their noise is small and their initial values are Ti0's.
    """
    ti0 = values.get("Ti0", 21.0)
    start = {}
    if "Ts" in extra and "Ris" not in values:
        start.update(Ris=0.01, Cs=0.001, pTs=-15.0, Ts0=ti0)
    if "Th" in extra and "Rih" not in values:
        start.update(Rih=0.01, Ch=0.001, pTh=-15.0, Th0=ti0)
    if "Tm" in extra and "Rim" not in values:
        start.update(Rim=90.0, Cm=1.0, pTm=-15.0, Tm0=ti0)
    if "Te" in extra and "Rie" not in values and "Ria" in values:
        start.update(Rie=values["Ria"] / 2, Rea=values["Ria"] / 2, Ce=0.01, pTe=-15.0, Te0=ti0)
    return start


def _model_files() -> dict:
    folder = resources.files(__package__).joinpath("models")
    return {f.name[: -len(".toml")]: f for f in folder.iterdir() if f.name.endswith(".toml")}


#: Walls listed by [`names()`][greyid.library.names]; ``wallN`` loads the N-node wall for any N
#: ([`wall_model()`][greyid.library.walls.wall_model]).
WALL_MODELS = ("wall1", "wall2")


def names() -> list[str]:
    """Every model in the library.

    Returns
    -------
    list of str
        Their names.
    """
    return list(BUILDING_MODELS) + list(WALL_MODELS) + sorted(_model_files())


def load_model(name: str) -> Model:
    """A fresh copy of a library model.

    Parameters
    ----------
    name : str
        One of [`names()`][greyid.library.names], or an RC network by its states
        in any order (``"TiTeTh"``, ``"TiThTe"``).

    Returns
    -------
    Model
        The model, with its units, bounds, derived quantities and nested-start rule.

    Raises
    ------
    ModelError
        An unknown name (the message lists the library).
    """
    states = _rc_states(name)
    if states is not None:
        return rc_network(states)
    if name.startswith("wall") and name[4:].isdigit() and int(name[4:]) >= 1:
        return wall_model(int(name[4:]))
    files = _model_files()
    if name not in files:
        raise ModelError(f"no model '{name}' in the library; available: {names()}")
    return Model.from_toml(files[name].read_text(encoding="utf-8"))


def available() -> dict[str, str]:
    """The library's models with their descriptions.

    Returns
    -------
    dict
        ``{name: description}``.
    """
    return {name: load_model(name).description for name in names()}


__all__ = ["available", "load_model", "names", "rc_network", "BUILDING_MODELS", "RC_STATES", "WALL_MODELS",
           "wall_model", "lumped_wall", "wall_frequency_response", "ladder_polynomials"]
