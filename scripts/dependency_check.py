"""Fit a small model with whatever JAX, NumPy and pandas are installed; print the versions and the answer.

Run by ``.ci/dependency-ends`` on the lowest releases pyproject.toml admits and on the newest, whose
answers must agree: ``python scripts/dependency_check.py`` prints one line,
``jax jaxlib numpy pandas loglik converged building-loglik``.
"""

import contextlib
import io

import numpy as np
import pandas as pd

import greyid


def main() -> None:
    import jax
    import jaxlib

    m = greyid.Model("ou")
    m.add_inputs("u")
    m.add_system("dx = (-a*x + b*u)*dt + s*dw1")
    m.add_observation("y = x", variance="e^2")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[0.1]])
    for name, value in dict(a=0.5, b=1.0, s=0.3, e=0.1).items():
        m.set_parameter(name, init=value * 1.3, lower=value / 100, upper=value * 100)
    rng = np.random.default_rng(0)
    plan = pd.DataFrame({"t": np.arange(200) * 0.5, "u": np.repeat(rng.normal(size=20), 10)})
    simulated = m.simulate(dict(a=0.5, b=1.0, s=0.3, e=0.1), plan, seed=1, method="exact")
    fit = m.fit(plan.assign(y=simulated.outputs[0, :, 0]))
    # The bundled building model: units (Pint), its CSV (pandas), its summary and report tables.
    from greyid.datasets import building_model, load_building_data

    building = building_model().fit(load_building_data().iloc[:300])
    assert "kWh/K" in building.summary()
    from greyid.cli import main as command_line

    # The command line (typer on click): help, and bad input answered with exit code 2.
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert command_line(["--help"]) == 0
        assert command_line(["fit", "no-such-model.toml"]) == 2
    print(jax.__version__, jaxlib.__version__, np.__version__, pd.__version__, f"{fit.loglik:.6f}", fit.converged,
          f"{building.loglik:.6f}")


if __name__ == "__main__":
    main()
