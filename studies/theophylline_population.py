"""Population fit of the theophylline data beside R's nlme (Pinheiro & Bates 2000, section 6.4).

    python studies/theophylline_population.py [--no-r]

Twelve subjects, eleven concentrations each (the data set ``theophylline``,
``greyid.datasets.fetch``: downloaded once, or read from ``GREYID_DATA_MIRROR``).  The
model is one compartment with first-order absorption (greyid.datasets.reference.
theophylline_model: the SDE with a process noise of 1e-4, its solution the ODE's
SSfol), random effects on lKa and lCl (normal on the log scale, Ω diagonal), as
nlme's ``fm2Theo.nlme`` with ``method = "ML"``.  greyid maximises the Laplace
approximation of the marginal likelihood; nlme alternates a linearisation about
the conditional modes (Lindstrom & Bates 1990).  Where Rscript and nlme are
installed (Debian: apt-get install r-base-core r-cran-nlme) the script runs
nlme on the same file and prints both side by side, with greyid's Laplace
approximation also evaluated at nlme's estimates.
"""

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

R_SCRIPT = """
suppressMessages(library(nlme))
d <- read.csv("{path}")
g <- groupedData(conc ~ Time | Subject, data = d)
fm <- nlme(conc ~ SSfol(Dose, Time, lKe, lKa, lCl), data = g, fixed = lKe + lKa + lCl ~ 1,
           random = pdDiag(lKa + lCl ~ 1), start = c(lKe = -2.5, lKa = 0.5, lCl = -3), method = "ML")
f <- fixef(fm); se <- sqrt(diag(vcov(fm))); sd <- as.numeric(VarCorr(fm)[, "StdDev"])
cat(sprintf("%s %.10g %.10g\\n", names(f), f, se), sep = "")
cat(sprintf("omega_lKa %.10g NA\\nomega_lCl %.10g NA\\ns2 %.10g NA\\n", sd[1], sd[2], sd[3]^2))
cat(sprintf("loglik %.10g NA\\n", as.numeric(logLik(fm))))
cat(sprintf("version %s NA\\n", as.character(packageVersion("nlme"))))
"""


def run_nlme(frame: pd.DataFrame) -> dict | None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "Theoph.csv"
        frame.to_csv(path, index=False)
        try:
            out = subprocess.run(["Rscript", "-e", R_SCRIPT.format(path=path)], capture_output=True, text=True,
                                 timeout=300, check=True).stdout
        except (OSError, subprocess.SubprocessError):
            return None
    return {name: (value, se) for name, value, se in (line.split() for line in out.strip().splitlines())}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-r", action="store_true", help="do not run R's nlme")
    args = parser.parse_args()
    import greyid
    from greyid.datasets.reference import theophylline_model
    from greyid.population.fit import Outer, _prepare_members, population_filter, population_programs
    from greyid.population.spec import make_spec

    frame = greyid.datasets.fetch("theophylline")
    data = {str(k): g[["Time", "Dose", "conc"]].reset_index(drop=True) for k, g in frame.groupby("Subject", sort=False)}
    model = theophylline_model()
    random = {"lKa": "normal", "lCl": "normal"}
    start = time.perf_counter()
    fit = greyid.fit_population(model, data, random, time="Time")
    seconds = time.perf_counter() - start
    print(fit.summary())
    print(f"\ngreyid.fit_population: {seconds:.1f} s")
    nlme = None if args.no_r else run_nlme(frame)
    if nlme is None:
        print("R's nlme not run")
        return
    rows = []
    for name in ["lKe", "lKa", "lCl", "s2", "omega_lKa", "omega_lCl"]:
        value, se = nlme[name]
        rows.append(dict(parameter=name, greyid=fit.params.loc[name, "estimate"],
                         greyid_se=fit.params.loc[name, "std_error"], nlme=float(value),
                         nlme_se=float(se) if se != "NA" else np.nan))
    # greyid's Laplace approximation at nlme's estimates
    spec, raw = make_spec(model, random, None, None, "diagonal", list(data))
    members = _prepare_members(model, list(data), list(data.values()), spec, raw, "Time", "zoh", None, None)
    options = population_filter(model, spec, members, None, "Time", "zoh", None, {})
    outer = Outer(population_programs(model.structure, spec, options), members, spec)
    at = {n: float(nlme[n][0]) for n in ["lCl", "lKa", "lKe", "s2", "omega_lKa", "omega_lCl"]}
    phi = np.array([at["lCl"], at["lKa"], at["lKe"], np.log(at["s2"]), np.log(at["omega_lKa"]),
                    np.log(at["omega_lCl"])])
    laplace_at_nlme = -outer.value(phi)[0]
    outer.close()
    rows.append(dict(parameter="loglik", greyid=fit.loglik, greyid_se=np.nan, nlme=float(nlme["loglik"][0]),
                     nlme_se=np.nan))
    table = pd.DataFrame(rows).set_index("parameter")
    print(f"\nside by side with R nlme {nlme['version'][0]} (method = 'ML'):")
    print(table.to_string(float_format=lambda v: f"{v:.5f}"))
    print(f"\nLaplace log-likelihood at nlme's estimates: {laplace_at_nlme:.5f} "
          f"(at greyid's: {fit.loglik:.5f}; nlme's own, Lindstrom-Bates: {float(nlme['loglik'][0]):.5f})")


if __name__ == "__main__":
    main()
