"""The thesis' test cell (section 7.2, model 7.43): simulate one series, fit, validate, report.

Run from the repository root:  python examples/test_cell.py [OUT_DIR]   (default out/test_cell)
"""

from __future__ import annotations

import sys
from pathlib import Path

from greyid.datasets.thesis import TEST_CELL_PARAMETERS, test_cell_inputs, test_cell_model


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/test_cell")
    out.mkdir(parents=True, exist_ok=True)
    model = test_cell_model()  # the library's "test_cell" model file
    data = test_cell_inputs(seed=1)  # 1512 samples at 20 min, PRBS heating, outdoor temperature
    simulated = model.simulate(TEST_CELL_PARAMETERS, data, method="exact", seed=1)
    data["Ttr"] = simulated.outputs[0, :, 0]
    data.to_csv(out / "test_cell.csv", index=False)

    fit = model.fit(data, progress=True)
    print(fit.summary())
    print(fit.derived().assign(truth=[55.29 * 13.86 / (55.29 + 13.86),
                                      (325.0 + 55.29 * 387.8 / (13.86 + 55.29)) * 3600 / 1e6]))
    print(fit.validate().summary())
    fit.save(out / "fit.json")
    fit.report(out / "report.html")
    print(f"wrote {out / 'fit.json'} and {out / 'report.html'}")


if __name__ == "__main__":
    main()
