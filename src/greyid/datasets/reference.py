"""Models of other tools' published examples, for cross-checks on the data sets they were fitted to.

The data themselves are not bundled (their licences are not ours to grant):
``greyid.datasets.fetch`` reads them by name (``"armadillo"``, ``"ornstein_2d"``,
``"theophylline"``).
"""

from __future__ import annotations

from ..api import Model


def armadillo_model(with_bounds: bool = True) -> Model:
    """pySIP's TwTi_RoRi for the Armadillo box: wall (Tw) and indoor (Ti) states,
    inputs T_ext and P_hea, process noise on the wall only, Ti0 = 26.70 °C and
    initial standard deviations 0.1 °C fixed; time in seconds."""
    m = Model("TwTi_RoRi")
    m.add_system("dTw = (1/(Cw*Ro)*(T_ext-Tw) + 1/(Cw*Ri)*(Ti-Tw))*dt + sigw*dw1")
    m.add_system("dTi = (1/(Ci*Ri)*(Tw-Ti) + P_hea/Ci)*dt")
    m.add_inputs("T_ext", "P_hea")
    m.add_observation("T_int = Ti", variance="sigv^2")
    m.set_initial_state(mean={"Tw": "Tw0", "Ti": 26.70}, covariance=[0.1**2, 0.1**2])
    if with_bounds:
        inits = dict(Ro=(0.01, 1e-4, 1.0), Ri=(0.005, 1e-4, 1.0), Cw=(1e7, 1e5, 1e9), Ci=(1e6, 1e4, 1e8),
                     sigw=(1e-3, 1e-6, 1.0), sigv=(0.05, 1e-4, 1.0), Tw0=(26.0, 20.0, 35.0))
        for name, (init, lower, upper) in inits.items():
            m.set_parameter(name, init=init, lower=lower, upper=upper)
    return m


def ornstein_2d_model() -> Model:
    """ctsmTMB's create.Ornstein2D.model: rates and noise levels on a log scale, mu direct."""
    m = Model("ornstein2d")
    m.add_system("dx1 = exp(logtheta)*(mu + u - x1)*dt + exp(logsx1)*dw1")
    m.add_system("dx2 = exp(logalpha)*(x1 - x2)*dt + exp(logsx2)*dw2")
    m.add_inputs("u")
    m.add_observation("y1 = x1", variance="exp(logsy1)^2")
    m.add_observation("y2 = x2", variance="exp(logsy2)^2")
    m.set_initial_state(mean={"x1": 3.0, "x2": 3.0}, covariance=[0.1, 0.1])
    for name, init in dict(logtheta=0.0, mu=1.0, logalpha=0.0, logsx1=-1.0, logsx2=-1.0,
                           logsy1=-2.0, logsy2=-2.0).items():
        m.set_parameter(name, init=init, lower=-10.0, upper=10.0)
    return m


def theophylline_model(process_noise: float = 1e-4) -> Model:
    """One compartment with first-order absorption and elimination (Pinheiro & Bates 2000, section 6.4;
    R's ``SSfol``) as an SDE: C' = Dose·ka·ke/Cl·e^{−ka t} − ke·C, C(0) = 0, parameters on the log scale
    (lKe, lKa, lCl) as nlme estimates them, residual variance s2, and a small fixed process noise
    ``sig`` so that the SDE's solution is the ODE's (the data: ``greyid.datasets.fetch("theophylline")``)."""
    m = Model("theophylline")
    m.add_system("dC = (Dose*exp(lKa + lKe - lCl - exp(lKa)*t) - exp(lKe)*C)*dt + sig*dw1")
    m.add_inputs("Dose")
    m.add_observation("conc = C", variance="s2")
    m.set_initial_state(mean={"C": 0.0}, covariance=[[0.0]])
    m.set_parameter("lKe", init=-2.5)
    m.set_parameter("lKa", init=0.5)
    m.set_parameter("lCl", init=-3.0)
    m.set_parameter("s2", init=0.5, lower=0)
    m.set_parameter("sig", init=process_noise, fixed=True)
    return m
