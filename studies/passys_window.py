"""Case 1 of the thesis (section 7.4): a PASSYS test cell with a window component, calibration then test.

    python studies/passys_window.py [--days 30] [--seed 0] [--figure cpgram.png]
    python studies/passys_window.py --data DIR     # your calibration.csv and test.csv

The original measurements are not public: both experiments are simulated
here from a network model in the spirit of figure 7.13 (the thesis gives its
structure and table 7.6, not every parameter), with solar inputs from pvlib for
a vertical south façade, and the four situations of table 7.6 are fitted:
fixed/ML versus MAP/ML, linear (7.53) versus nonlinear (7.52) solar
transmittance.

Network (W, Wh/K, hours, °C): test-room air Ta exchanges with the envelope
Tv (H_av), the envelope with the outdoor surface temperature Tes (H_ve); the air
with the partition wall Tp (H_ap), the partition with the service-room air
Tsr (H_ps); the heating qh enters the air.  The test component: the air with
its internal surface Ts through H_psc1 (fixed, as in the thesis), the surface
with the component's core Tc (H_s), the core with the outdoor air Tea (H_c);
the solar gain through the window enters the surface, f = A_dif G_dif +
A_dir F(θ, α_eff) G_dir (nonlinear, F the glazing transmittance of α_eff
panes) or A_tot (G_dif + G_dir) (linear).  Outputs: Ta and Ts.

The calibration experiment replaces the component by a wall whose heat loss
q_cal is measured (an input); its service room varies little and slowly
(T_sr badly excited, as in the thesis), so the partition's H_ap, H_ps come out
vague.  The prior of the test experiment is that fit's (``fit.to_prior``).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import greyid  # noqa: E402
from greyid.data.solar import solar_inputs  # noqa: E402
from greyid.validation.spectral import cumulative_periodogram, cumulative_periodogram_test  # noqa: E402

#: The simulation's parameters (W/K, Wh/K, W/m²-scaled apertures in m², noise).
TRUE = dict(H_av=18.0, H_ve=9.0, C_a=120.0, C_v=2200.0, H_ap=6.0, H_ps=4.0, C_p=300.0,
            H_psc1=25.0, H_s=12.0, H_c=9.0, C_s=20.0, C_c=40.0, A_dif=0.55, A_dir=0.75, alpha=2.0)
NOISE = dict(s_a=0.05, s_v=0.03, s_p=0.03, s_s=0.08, s_c=0.05, e_a=0.01, e_s=0.02)
ENVELOPE = ["H_av", "H_ve", "C_a", "C_v", "H_ap", "H_ps", "C_p"]  # from the calibration experiment
PARTITION = ["H_ap", "H_ps"]

UNITS = {"t": "h", "qh": "W", "q_cal": "W", "Gdif": "W/m^2", "Gdir": "W/m^2", "Tes": "degC", "Tsr": "degC",
         "Tea": "degC", "Ta": "degC", "Tv": "degC", "Tp": "degC", "Ts": "degC", "Tc": "degC", "yTa": "degC",
         "yTs": "degC", **{h: "W/K" for h in ("H_av", "H_ve", "H_ap", "H_ps", "H_psc1", "H_s", "H_c")},
         **{c: "Wh/K" for c in ("C_a", "C_v", "C_p", "C_s", "C_c")}, "A_dif": "m^2", "A_dir": "m^2",
         "A_tot": "m^2", **{s: "K/h^0.5" for s in ("s_a", "s_v", "s_p", "s_s", "s_c")}, "e_a": "K^2",
         "e_s": "K^2"}


def envelope_equations(air_extra: str = "") -> list[str]:
    return [f"dTa = ((Tv - Ta)*H_av + (Tp - Ta)*H_ap + qh{air_extra})/C_a*dt + exp(s_a)*dw1",
            "dTv = ((Ta - Tv)*H_av + (Tes - Tv)*H_ve)/C_v*dt + exp(s_v)*dw2",
            "dTp = ((Ta - Tp)*H_ap + (Tsr - Tp)*H_ps)/C_p*dt + exp(s_p)*dw3"]


def calibration_model() -> greyid.Model:
    m = greyid.Model("calibration", "Test cell with the calibration wall (heat loss q_cal measured)")
    m.add_system(*envelope_equations(" - q_cal"))
    m.add_inputs("qh", "q_cal", "Tes", "Tsr")
    m.add_observation("yTa = Ta", variance="exp(e_a)")
    m.set_initial_state(mean={"Ta": "Ta0", "Tv": "Tv0", "Tp": "Tp0"}, covariance=[[0.01, 0, 0], [0, 0.01, 0],
                                                                                  [0, 0, 0.01]])
    _parameters(m, ENVELOPE, noise=("s_a", "s_v", "s_p", "e_a"), states=("Ta0", "Tv0", "Tp0"))
    m.set_units({k: v for k, v in UNITS.items() if k in set(ENVELOPE) | {"t", "qh", "q_cal", "Tes", "Tsr",
                                                                         "Ta", "Tv", "Tp", "yTa", "s_a",
                                                                         "s_v", "s_p", "e_a"}})
    return m


def component_model(nonlinear: bool) -> greyid.Model:
    m = greyid.Model("window_" + ("nonlinear" if nonlinear else "linear"),
                     "Test cell with the window component (figure 7.13)")
    gain = ("A_dif*Gdif + A_dir*glazing_transmittance(theta, alpha)*Gdir" if nonlinear
            else "A_tot*(Gdif + Gdir)")
    m.add_system(*envelope_equations(" + (Ts - Ta)*H_psc1"),
                 f"dTs = ((Ta - Ts)*H_psc1 + (Tc - Ts)*H_s + {gain})/C_s*dt + exp(s_s)*dw4",
                 "dTc = ((Ts - Tc)*H_s + (Tea - Tc)*H_c)/C_c*dt + exp(s_c)*dw5")
    m.add_inputs("qh", "Tes", "Tsr", "Tea", "Gdif", "Gdir", "theta")
    m.add_observation("yTa = Ta", variance="exp(e_a)")
    m.add_observation("yTs = Ts", variance="exp(e_s)")
    states = ("Ta0", "Tv0", "Tp0", "Ts0", "Tc0")
    m.set_initial_state(mean={s[:-1]: s for s in states}, covariance=(np.eye(5) * 0.01).tolist())
    solar = ["A_dif", "A_dir", "alpha"] if nonlinear else ["A_tot"]
    _parameters(m, ENVELOPE + ["H_s", "H_c", "C_s", "C_c"] + solar,
                noise=("s_a", "s_v", "s_p", "s_s", "s_c", "e_a", "e_s"), states=states)
    m.set_parameter("H_psc1", init=TRUE["H_psc1"], fixed=True)
    m.set_parameter("alpha", init=1.5, lower=0.2, upper=8.0) if nonlinear else None
    m.set_parameter("A_tot", init=0.5, lower=0.0, upper=5.0) if not nonlinear else None
    units = dict(UNITS, theta="rad")
    m.set_units({k: v for k, v in units.items() if k in set(m.parameter_names) | set(m.input_names)
                 | set(m.state_names) | set(m.output_names) | {"t"}})
    return m


def _parameters(m, physical, noise, states):
    for name in physical:
        value = TRUE.get(name, 0.6)
        m.set_parameter(name, init=value * 1.2, lower=value / 20, upper=value * 20)
    for name in noise:
        # Below e^-10 a process noise intensity (K/√h) or a measurement variance (K²) is nil on
        # this problem's scale: the likelihood is flat beyond, and a fit drifting there would end
        # in that flat stretch rather than at the bound that says "no noise here".
        m.set_parameter(name, init=np.log(0.05), lower=-10.0, upper=5.0)
    for name in states:
        m.set_parameter(name, init=20.0, lower=-20.0, upper=60.0)


def climate(days: int, seed: int) -> pd.DataFrame:
    """Hourly outdoor climate on a vertical south façade (pvlib geometry, clear sky times clouds)."""
    import pvlib

    rng = np.random.default_rng(seed)
    times = pd.date_range("2026-03-01", periods=24 * days, freq="h", tz="Europe/Brussels")
    site = pvlib.location.Location(45.8, 8.6, tz="Europe/Brussels")  # Ispra, a PASSYS site
    clear = site.get_clearsky(times)["ghi"].to_numpy()
    clouds = np.clip(np.repeat(rng.uniform(0.2, 1.0, days), 24) + 0.1 * rng.normal(size=24 * days), 0.05, 1.0)
    sun = solar_inputs(times, 45.8, 8.6, tilt=90, azimuth=180, ghi=clear * clouds)
    hours = np.arange(24 * days, dtype=float)
    weather = np.cumsum(rng.normal(0, 0.15, 24 * days))
    t_air = 8 + 5 * np.sin(2 * np.pi * (hours - 9) / 24) + weather
    return pd.DataFrame({"t": hours, "Tea": t_air, "Tes": t_air + 0.004 * sun["global"].to_numpy(),
                         "Gdif": sun["diffuse"].to_numpy(), "Gdir": sun["beam"].to_numpy(),
                         "theta": sun["incidence_rad"].to_numpy()})


def heating(n: int, seed: int, clock: int = 6) -> np.ndarray:
    rng = np.random.default_rng(seed + 7)
    return 120.0 * np.repeat(rng.integers(0, 2, n // clock + 1), clock)[:n]


def experiments(days: int = 30, seed: int = 0):
    """The simulated calibration and test experiments (DataFrames)."""
    names = dict(TRUE, **{k: np.log(v) for k, v in NOISE.items()})
    base = climate(days, seed)
    n = len(base)
    rng = np.random.default_rng(seed + 1)
    calibration = base.assign(qh=heating(n, seed))
    # The service room varies little and slowly in the calibration (T_sr badly excited, ±1 K over three days):
    # the partition wall comes out vague.
    calibration["Tsr"] = 20.0 + 1.0 * np.sin(2 * np.pi * base["t"] / 72) + 0.05 * rng.normal(size=n)
    calibration["q_cal"] = 2.5 * (20.0 - base["Tea"])  # the calibration wall's measured loss (W)
    cal = calibration_model()
    truth = {k: names[k] for k in cal.parameter_names if k in names}
    truth.update(Ta0=20.0, Tv0=15.0, Tp0=20.0)
    sim = cal.simulate(truth, calibration, method="exact", seed=seed + 2)
    calibration["yTa"] = sim.outputs[0, :, 0]
    test = climate(days, seed + 10).assign(qh=heating(n, seed + 10))
    test["Tsr"] = 18.0 + 3.0 * np.repeat(np.random.default_rng(seed + 3).integers(0, 2, n // 12 + 1), 12)[:n]
    comp = component_model(nonlinear=True)
    truth = {k: names[k] for k in comp.parameter_names if k in names}
    truth.update(Ta0=20.0, Tv0=15.0, Tp0=19.0, Ts0=20.0, Tc0=12.0)
    sim = comp.simulate(truth, test, method="euler", substeps=20, seed=seed + 4)
    test["yTa"], test["yTs"] = sim.outputs[0, :, 0], sim.outputs[0, :, 1]
    return calibration, test


#: Table 7.6's physical characteristics as functions of the parameters (W/K, Wh/K, m²): steady-state
#: transmissions of the series paths, and the heat stored in each path when T_a rises 1 K.
SERIES = "1/(1/{a} + 1/{b})"
CHARACTERISTICS = {
    "UA_tr,e [W/K]": SERIES.format(a="H_av", b="H_ve"),
    "CI_tr,e [Wh/K]": "C_a + C_v*H_av/(H_av + H_ve)",
    "UA_tr,sr [W/K]": SERIES.format(a="H_ap", b="H_ps"),
    "CI_tr,sr [Wh/K]": "C_p*H_ap/(H_ap + H_ps)",
    "UA_psc [W/K]": "1/(1/H_psc1 + 1/H_s + 1/H_c)",
    "CI_psc [Wh/K]": "(C_s*(1/H_s + 1/H_c) + C_c/H_c)/(1/H_psc1 + 1/H_s + 1/H_c)",
}
#: gA for 25 % diffuse radiation and the beam at 45° (the thesis' convention).
SOLAR = {"non-linear": {"gA_psc [m2]": "0.25*A_dif + 0.75*A_dir*glazing_transmittance(pi/4, alpha)",
                        "alpha_eff": "alpha"},
         "linear": {"gA_psc [m2]": "A_tot"}}


def characteristics(fit, label: str) -> pd.DataFrame:
    """Table 7.6's characteristics with delta-method standard errors (``fit.derived``)."""
    return fit.derived({**CHARACTERISTICS, **SOLAR[label]})[["estimate", "std_error"]]


def true_characteristics() -> dict:
    import sympy as sp

    from greyid.model.equations import parse_expression

    values = {sp.Symbol(name, real=True): value for name, value in TRUE.items()}
    return {name: float(parse_expression(text).subs(values).evalf())
            for name, text in {**CHARACTERISTICS, **SOLAR["non-linear"]}.items()}


def situations(calibration, test):
    """The four fits of table 7.6 and the calibration fit."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal_fit = calibration_model().fit(calibration, starts=2)
    # A parameter the calibration left at a bound has no standard error: no Gaussian prior for it
    # (MAP leaves it free), and fixing takes the calibration's value all the same.
    known = [n for n in ENVELOPE if np.isfinite(cal_fit.bse[n]) and cal_fit.bse[n] > 0]
    prior = cal_fit.to_prior(names=known)
    fits = {}
    for nonlinear in (False, True):
        label = "non-linear" if nonlinear else "linear"
        fixed = component_model(nonlinear)
        for name in ENVELOPE:
            fixed.set_parameter(name, init=cal_fit.values[name], fixed=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fits[(label, "fixed/ML")] = fixed.fit(test)
            fits[(label, "MAP/ML")] = component_model(nonlinear).fit(test, criterion="map", prior=prior)
    return cal_fit, fits


def table(fits, cal_fit) -> pd.DataFrame:
    """Table 7.6 for the four situations, value (standard error), beside the simulation's truth; the
    mean and variance of the one-step prediction errors of T_s, log L, and the cumulative periodogram
    test of both outputs' residuals (figure 7.16).  Where fixed/ML fixes the envelope its
    characteristics and their standard errors are the calibration's."""
    envelope = cal_fit.derived({k: v for k, v in CHARACTERISTICS.items() if "_tr," in k})[["estimate", "std_error"]]
    rows = {}
    for (label, how), fit in fits.items():
        values = characteristics(fit, label)
        if how == "fixed/ML":
            values.loc[envelope.index] = envelope
        column = {name: f"{v:.4g} ({se:.2g})" for name, (v, se) in values.iterrows()}
        errors = fit.filter().innovations["yTs"]
        column.update({"mean p.e. (Ts)": f"{errors.mean():.4f}", "var p.e. (Ts)": f"{errors.var():.4f}",
                       "log L": f"{fit.loglik:.1f}", "converged": str(fit.converged)})
        for output in ("yTa", "yTs"):
            test = cumulative_periodogram_test(fit.residuals[output])
            column[f"cum. periodogram p ({output[1:]})"] = f"{test.p_value:.2g}"
        rows[f"{label} {how}"] = column
    rows["truth"] = {name: f"{value:.4g}" for name, value in true_characteristics().items()}
    frame = pd.DataFrame(rows).fillna("")
    first = [*CHARACTERISTICS, *SOLAR["non-linear"]]
    return frame.loc[first + [name for name in frame.index if name not in first]]


def plot_periodograms(fit, path: str) -> None:
    """Figure 7.16: the cumulative periodograms of both outputs' residuals with 95 % and 99 % bands."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    for output in ("yTa", "yTs"):
        cp = cumulative_periodogram(fit.residuals[output], dt=1.0)
        ax.plot(cp.index, cp["cumulative"], label=output[1:])
    for band, style in (("band_95%", "--"), ("band_99%", ":")):
        for sign in (-1, 1):
            ax.plot(cp.index, cp["white"] + sign * cp[band], "k" + style, lw=0.8,
                    label=f"{band[5:]} band" if sign > 0 else None)
    ax.set(xlabel="frequency [1/h]", ylabel="cumulative periodogram", title="residuals, non-linear MAP/ML")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", type=Path, default=None,
                        help="a directory with your calibration.csv and test.csv (the models' columns, t in hours)")
    parser.add_argument("--figure", default=None, help="write figure 7.16 (non-linear MAP/ML) to this file")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    if args.data is None:
        calibration, test = experiments(args.days, args.seed)
    else:
        calibration, test = (pd.read_csv(args.data / f"{name}.csv") for name in ("calibration", "test"))
    cal_fit, fits = situations(calibration, test)
    print(f"calibration fit: log L {cal_fit.loglik:.2f}; partition H_ap = {cal_fit.values['H_ap']:.3g} "
          f"± {cal_fit.bse['H_ap']:.2g}, H_ps = {cal_fit.values['H_ps']:.3g} ± {cal_fit.bse['H_ps']:.2g} "
          f"(truth {TRUE['H_ap']}, {TRUE['H_ps']}; '± nan': at a bound, no prior for it)")
    pd.set_option("display.width", 160)
    print(table(fits, cal_fit).to_string())
    if args.figure:
        plot_periodograms(fits[("non-linear", "MAP/ML")], args.figure)
    print(f"({time.perf_counter() - started:.0f} s)")


if __name__ == "__main__":
    main()
