"""What an estimated delay costs: the fuel-film model (8.1)–(8.3) with and without ``delay(mfi, delta_t)``.

    python benchmarks/delays.py

One operating point of table 8.2 (s60g4: 3000 samples at 12.5 ms, PRBS on the
injected fuel), simulated once; then for the library model (delay estimated)
and the same model with the delay fixed at a whole number of samples written
as a shifted column (no delay): the compiled log-likelihood, its gradient and
its Hessian (first call and compiled), and a fit from the library's start.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
from timing import timed  # noqa: E402


def main():
    import jax
    import jax.numpy as jnp
    import numpy as np

    import fuel_film
    from greyid import Model, library
    from greyid.data import prepare_series
    from greyid.filters.api import compiled_filter, filter_inputs, filter_options

    warnings.simplefilter("ignore")
    point = fuel_film.TABLE_8_2.loc["s60g4"]
    data = fuel_film.experiment(point, seed=0)
    delayed = library.load_model("fuel_film")
    # The same model file with the input itself in place of its delayed copy.
    text = delayed.to_toml().replace("delay(mfi, delta_t)", "mfi")
    plain = Model.from_toml("\n".join(line for line in text.splitlines() if not line.startswith("delta_t")))
    shift = 3  # samples: 37.5 ms, table 8.2's delay on the grid
    shifted = data.assign(mfi=np.concatenate([np.full(shift, data["mfi"].iloc[0]), data["mfi"].to_numpy()[:-shift]]))
    truth = fuel_film.truth(point)
    for label, model, frame, params in (("with delay(mfi, delta_t)", delayed, data, truth),
                                        ("without (shifted column)", plain, shifted,
                                         {k: v for k, v in truth.items() if k != "delta_t"})):
        print(label)
        s = model.structure
        inputs = filter_inputs(prepare_series(frame, s.input_names, s.output_names), "zoh")
        theta = jnp.asarray(model.parameter_vector(params))
        run = compiled_filter(s, filter_options(s, "kalman"), keep_outputs=False)
        value = jax.jit(lambda th: run(th, inputs)[0].loglik.sum())
        for name, fun in (("log-likelihood", value), ("gradient", jax.jit(jax.grad(value))),
                          ("Hessian", jax.jit(jax.hessian(value)))):
            timed(name, lambda: jax.block_until_ready(fun(theta)), repeat=5)
        fit = timed("fit", lambda: model.fit(frame), repeat=0)
        print(f"  log L {fit.loglik:.2f}, {fit.iterations} iterations, converged {fit.converged}")


if __name__ == "__main__":
    main()
