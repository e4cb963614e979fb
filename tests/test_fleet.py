"""Fleets (greyid.fit_many) and the batched searches they share with multi-start fits."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.datasets.building import TRUE_PARAMETERS, building_model, load_building_data
from greyid.estimate.batch import drive, pad_series, prune_trailing
from greyid.estimate.optimize import EXACT, SCORING, run_alone
from greyid.estimate.trust_region import Search
from greyid.filters.api import filter_inputs
from greyid.data.prepare import prepare_series
from greyid.fleet import relate


@pytest.fixture(scope="module")
def fleet_model():
    """The bundled building model with its flat noise term fixed, compiled once for the module."""
    model = building_model()
    model.set_parameter("p22", init=-4.0, fixed=True)
    return model


@pytest.fixture(scope="module")
def houses(fleet_model):
    """Three houses of different lengths simulated from the bundled model; one has gaps in its output."""
    data = load_building_data()
    sim = fleet_model.simulate(TRUE_PARAMETERS, data, n_paths=3, seed=11)
    out = {}
    for k, rows in enumerate((300, 260, 220)):
        frame = data.iloc[:rows].copy()
        frame["yTi"] = sim.outputs[k, :rows, 0]
        out[f"house{k}"] = frame
    out["house1"].loc[[5, 6, 40, 100], "yTi"] = np.nan
    return out


@pytest.fixture(scope="module")
def fleet(fleet_model, houses):
    return greyid.fit_many(fleet_model, houses)


def test_fleet_equals_separate_fits(fleet_model, houses, fleet):
    """Each member of a batched fleet fit reaches what its own model.fit reaches (lengths and gaps differ)."""
    for name, frame in houses.items():
        alone = fleet_model.fit(frame)
        member = fleet.fits[name]
        assert member.converged and alone.converged
        assert member.loglik == pytest.approx(alone.loglik, rel=1e-6)
        free = [p for p in alone.params.index if not alone.params.loc[p, "fixed"]]
        np.testing.assert_allclose(member.params.loc[free, "estimate"], alone.params.loc[free, "estimate"],
                                   rtol=1e-5, atol=1e-8)
        np.testing.assert_allclose(member.params.loc[free, "std_error"], alone.params.loc[free, "std_error"],
                                   rtol=1e-4)
        row = fleet.table.loc[name]
        assert row["loglik"] == member.loglik and row["Ci"] == member.values["Ci"]
        assert row["Ci_se"] == member.params.loc["Ci", "std_error"] and row["error"] is None
        assert row["aic"] == pytest.approx(member.aic) and row["n_obs"] == member.n_obs


def test_a_fleet_compiles_one_vectorised_size_as_its_members_converge(fleet_model):
    """As members converge fewer ask each round; the program compiled for the first round serves them
    (padded) rather than a new program per power of two, and each member reaches its own fit's optimum."""
    model = building_model()  # a structure of its own: nothing compiled for it yet
    model.set_parameter("p22", init=-4.0, fixed=True)
    data = load_building_data().iloc[:200]
    sim = model.simulate(TRUE_PARAMETERS, data, n_paths=6, seed=5)
    same_shape = {f"house{k}": data.assign(yTi=sim.outputs[k, :, 0]) for k in range(6)}
    fleet = greyid.fit_many(model, same_shape)
    batched = [programs for key, programs in model.structure.cache.items()
               if isinstance(key, tuple) and key[0] == "batched"]
    sizes = {size for programs in batched for key, signatures in programs.items()
             if isinstance(key, tuple) and key[0] == "compiled" for kind, size in signatures if kind == SCORING}
    assert len(sizes) == 1
    for name in ("house0", "house5"):
        alone = fleet_model.fit(same_shape[name])
        assert fleet.fits[name].loglik == pytest.approx(alone.loglik, rel=1e-6)
        free = ~alone.params["fixed"]  # p11 is nearly flat in 200 rows: compared in its standard errors
        gap = (fleet.fits[name].params["estimate"] - alone.params["estimate"])[free] / alone.params["std_error"][free]
        np.testing.assert_allclose(gap, 0.0, atol=1e-3)


def test_fleet_table_summary_and_plot(fleet):
    table = fleet.table
    assert list(table.index) == ["house0", "house1", "house2"]
    for column in ("Ci", "Ci_se", "loglik", "aic", "converged", "iterations", "error"):
        assert column in table.columns
    assert table["n_obs"].tolist() == [300, 256, 220]
    text = fleet.summary()
    assert "3 fitted, 3 converged, 0 failed" in text and "median" in text
    fig = fleet.plot()
    assert len([ax for ax in fig.axes if ax.get_visible()]) == len(fleet.estimates().columns)


def test_fleet_plot_tick_labels_do_not_overlap(fleet, monkeypatch):
    """Estimates in SI units (capacities ~1e7, resistances ~1e-3, spread in their fourth digit): the
    drawn tick labels of every panel keep apart."""
    import pandas as pd
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    rng = np.random.default_rng(3)
    spread = pd.DataFrame({"Cw": 1.5086e7 * (1 + 1e-3 * rng.normal(size=200)),
                           "Ro": 1.8427e-3 * (1 + 1e-3 * rng.normal(size=200)),
                           "Tw0": 26.588 + 1e-3 * rng.normal(size=200)})
    monkeypatch.setattr(fleet, "estimates", lambda: spread)
    fig = fleet.plot()
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    for ax in fig.axes:
        boxes = [label.get_window_extent(renderer) for label in ax.get_xticklabels() if label.get_text()]
        assert len(boxes) >= 2
        for left, right in zip(boxes, boxes[1:]):
            assert left.x1 < right.x0, f"{ax.get_xlabel()}: tick labels overlap"


def test_failed_data_sets_become_rows_with_their_error(fleet_model, houses):
    bad_column = houses["house0"].drop(columns=["Qi"])
    too_short = houses["house2"].iloc[:5]
    result = greyid.fit_many(fleet_model, {"good": houses["house2"], "no_Qi": bad_column, "short": too_short})
    table = result.table
    assert table.loc["good", "converged"] and table.loc["good", "error"] is None
    assert result.fits["no_Qi"] is None and not table.loc["no_Qi", "converged"]
    assert "data set 'no_Qi'" in table.loc["no_Qi", "error"] and "Qi" in table.loc["no_Qi", "error"]
    assert "data set 'short'" in table.loc["short", "error"] and "observed" in table.loc["short", "error"]
    assert "2 failed" in result.summary()


def test_list_of_datasets_init_per_dataset_and_paths(fleet_model, houses, tmp_path):
    """A list gets names 0..n−1; init per data set as a DataFrame; a CSV path is read where it is fitted."""
    path = tmp_path / "house2.csv"
    houses["house2"].to_csv(path, index=False)
    init = pd.DataFrame({"Ci": [1.5, 2.5], "Cw": [15.0, 25.0]}, index=[0, 1])
    result = greyid.fit_many(fleet_model, [houses["house0"], str(path)], init=init)
    assert list(result.table.index) == [0, 1]
    assert result.fits[1].loglik == pytest.approx(fleet_model.fit(houses["house2"]).loglik, rel=1e-6)
    assert result.fits[0].starts[0]["start"] == "initial values"
    with pytest.raises(greyid.DataError, match="init has no row for data set '1'"):
        greyid.fit_many(fleet_model, [houses["house0"], houses["house2"]], init=init.iloc[:1])
    with pytest.raises(greyid.DataError, match="mapping name"):
        greyid.fit_many(fleet_model, houses["house0"])


def test_progress_callback_counts_data_sets(fleet_model, houses):
    seen = []
    greyid.fit_many(fleet_model, {"a": houses["house2"]}, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(1, 1)]


def _quadratic_programs(center):
    def exact(z):
        d = z - center
        return 0.5 * d @ d + 0.25 * d[0] ** 4, d + np.array([d[0] ** 3, 0.0]), np.diag([1 + 3 * d[0] ** 2, 1.0])

    return exact


def test_drive_equals_searches_run_alone():
    """Searches driven together give exactly what each gives alone (own trust region, own convergence)."""
    centers = [np.array([1.0, -2.0]), np.array([-3.0, 0.5]), np.array([0.2, 0.2])]
    starts = [np.array([5.0, 5.0]), np.array([0.0, 0.0]), np.array([-4.0, 1.0])]
    alone = [run_alone(Search(z0), {EXACT: _quadratic_programs(c)}) for c, z0 in zip(centers, starts)]

    def evaluate(groups):
        return [[_quadratic_programs(centers[i])(z) for i, z in zip(members, Z)] for _, members, Z in groups]

    together = drive([Search(z0) for z0 in starts], evaluate)
    for a, b in zip(alone, together):
        np.testing.assert_array_equal(a.z, b.z)
        assert (a.iterations, a.evaluations, a.converged) == (b.iterations, b.evaluations, b.converged)


def test_prune_trailing_stops_only_far_behind_and_slow():
    class Fake:
        def __init__(self, f, iterations, history):
            self.f, self.iterations, self.history = f, iterations, history

    searches = [Fake(-1000.0, 9, [0, -900, -990, -1000]),  # the best
                Fake(-800.0, 9, [-799.5, -799.8, -799.9, -800]),  # 200 behind, settled (gaining 0.5): pruned
                Fake(-800.0, 9, [-790, -795, -799, -800]),  # 200 behind, still gaining 10: kept (a crawl may find more)
                Fake(-980.0, 9, [-979, -979.5, -980, -980]),  # 20 behind: kept
                Fake(-100.0, 3, [-99, -99, -100, -100])]  # too early to judge: kept
    assert set(prune_trailing(searches, {1, 2, 3, 4})) == {1}


def test_pad_series_changes_nothing(fleet_model, houses):
    """A series padded to a longer length has the same log-likelihood."""
    structure = fleet_model.structure
    series = prepare_series(houses["house2"], structure.input_names, structure.output_names, "t", None)
    inputs = filter_inputs(series, "zoh", on_device=False)
    padded = pad_series([inputs], len(inputs.t) + 37, len(inputs.unique_dt) + 3)
    one = pd.Series(TRUE_PARAMETERS)
    expected = fleet_model.loglik(one, houses["house2"])
    from greyid.filters.api import compiled_filter, filter_options

    run = compiled_filter(structure, filter_options(structure, None), False)
    theta = fleet_model.parameter_vector(TRUE_PARAMETERS)
    member = type(inputs)(*[np.asarray(leaf)[0] for leaf in padded])
    assert float(np.sum(run(theta, member)[0].loglik)) == pytest.approx(expected, rel=1e-12)


def test_interval_slots_of_regular_and_irregular_series(fleet_model, houses):
    """A regular series keeps its two sampling intervals (the first row's 0 and Δ) unpadded; one with
    a third interval is padded to four slots, and the filter reads the same intervals either way."""
    structure = fleet_model.structure
    data = houses["house2"]
    regular = filter_inputs(prepare_series(data, structure.input_names, structure.output_names, "t", None), "zoh",
                            on_device=False)
    step = float(np.diff(data["t"])[0])
    np.testing.assert_allclose(regular.unique_dt, [0.0, step], rtol=1e-11)  # (rounded to 12 digits)
    gap = data.drop(index=data.index[5])  # one interval of 2Δ
    irregular = filter_inputs(prepare_series(gap, structure.input_names, structure.output_names, "t", None), "zoh",
                              on_device=False)
    np.testing.assert_allclose(irregular.unique_dt, [0.0, step, 2 * step, 0.0], rtol=1e-11)
    np.testing.assert_allclose(irregular.unique_dt[irregular.dt_index][1:len(gap)], np.diff(gap["t"]), rtol=1e-11)


def test_relate_recovers_a_linear_relation_and_ranks_subsets():
    """WLS on covariates with weights 1/SE² (against NumPy), best subset by Mallows' C_p."""
    rng = np.random.default_rng(4)
    n = 40
    covariates = pd.DataFrame({"speed": rng.uniform(1, 5, n), "load": rng.uniform(0, 1, n),
                               "noise": rng.normal(size=n)}, index=[f"p{i}" for i in range(n)])
    se = rng.uniform(0.05, 0.2, n)
    X = 2.0 - 0.5 * covariates["speed"] + 1.5 * covariates["load"] + se * rng.normal(size=n)
    table = pd.DataFrame({"X": X, "X_se": se}, index=covariates.index)
    relation = relate(table, covariates, "X")
    assert relation.subsets.loc[0, "covariates"] == "speed, load"
    A = np.column_stack([np.ones(n), covariates["speed"], covariates["load"]]) / se[:, None]
    beta = np.linalg.lstsq(A, X / se, rcond=None)[0]
    np.testing.assert_allclose(relation.best.params.to_numpy(), beta, rtol=1e-10)
    assert len(relation.subsets) == 8
    with pytest.raises(greyid.DataError, match="covariate 'air'"):
        relate(table, covariates, "X", candidates=["air"])
    # A fleet of six: statsmodels' residual normality tests need eight, the summary says nan without a warning.
    few = relate(table.iloc[:6], covariates.iloc[:6], "X", candidates=["speed"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        text = few.summary()
    assert "best subset ['speed']" in text and "Omnibus:" in text


@pytest.mark.alone
def test_dask_local_cluster_equals_in_process(fleet_model, houses, fleet):
    """Chunks fitted on a real LocalCluster of two worker processes give the in-process table."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        remote = greyid.fit_many(fleet_model, houses, scheduler=client, chunk_size=2)
    columns = [c for c in fleet.table.columns if c not in ("message",)]
    pd.testing.assert_frame_equal(remote.table[columns], fleet.table[columns], rtol=1e-8)
    assert len(remote.fits["house1"].residuals) == len(houses["house1"])


def test_batched_starts_equal_the_same_starts_run_alone(fleet_model, houses):
    """A fit's starts run together reach exactly what each start reaches as a fit of its own."""
    from greyid.estimate.estimation import free_parameters
    from greyid.estimate.starts import space_filling

    data = houses["house0"]
    together = fleet_model.fit(data, starts=3, seed=5)
    parameters = free_parameters(fleet_model)
    points = [parameters.z0] + space_filling(parameters.transform, parameters.z0, 2, 5)
    free_names = [parameters.names[i] for i in parameters.free]
    assert together.starts[0]["converged"]
    for point, start in zip(points, together.starts):
        theta = parameters.transform.to_theta(point, np)
        alone = fleet_model.fit(data, init=dict(zip(free_names, theta)))
        if start["message"].startswith("pruned"):
            # Stopped on the way: below where the same start ends alone, and below the best start.
            assert start["criterion"] < alone.loglik and start["criterion"] < together.loglik - 50
            assert alone.loglik <= together.loglik + 1e-6
            continue
        assert start["criterion"] == pytest.approx(alone.loglik, rel=1e-9, abs=1e-9)
        assert start["iterations"] == alone.iterations
    # A pruned start is not counted as an optimum of its own.
    pruned = sum(s["message"].startswith("pruned") for s in together.starts)
    assert pruned >= 1
    assert f"{pruned} pruned" in together.start_spread() and "several optima" not in together.start_spread()


@pytest.mark.alone
def test_a_cluster_that_loses_every_worker_returns_failed_rows(fleet_model, houses):
    """Every worker of a LocalCluster killed (no nanny brings them back): fit_many must not wait for
    good.  The members whose chunks could not be computed come back as failed rows that say why, and
    the call returns."""
    import os
    import signal
    import time

    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        from distributed.core import Status

        for nanny in list(cluster.workers.values()):
            nanny.status = Status.closing_gracefully  # the nanny brings no new worker: none is left
            os.kill(nanny.process.process.pid, signal.SIGKILL)  # as a crash would end it
        deadline = time.monotonic() + 60
        while client.scheduler_info()["workers"] and time.monotonic() < deadline:
            time.sleep(0.1)
        started = time.monotonic()
        result = greyid.fit_many(fleet_model, houses, scheduler=client, chunk_size=1, worker_timeout=3.0)
        took = time.monotonic() - started
    assert took < 60
    assert len(result.failed) == len(houses)
    assert all("no worker" in text for text in result.failed)
    assert list(result.table.index) == list(houses)


def test_a_fleets_starts_are_those_of_a_separate_fit_reductions_included():
    """A library model that declares where it reduces to a smaller one: with starts > 1 each member starts
    there too, as model.fit does, so a member's fit is the fit a separate call gives."""
    from greyid import library

    model = library.load_model("TiTh")
    rng = np.random.default_rng(4)
    t = np.arange(150) * 0.25
    inputs = pd.DataFrame({"t": t, "Ta": 5 + 2 * np.sin(t / 4), "Ps": 0.0, "Ph": 2.0 * (np.sin(t) > 0)})
    data = model.simulate(model.initial_values(), inputs, seed=1).frame(0)[["t", "Ta", "Ps", "Ph", "yTi"]]
    data["yTi"] += 0.01 * rng.normal(size=len(data))
    fleet = greyid.fit_many(model, {"a": data}, starts=3, optimizer="newton")
    alone = model.fit(data, starts=3, optimizer="newton")
    labels = [s["start"] for s in fleet.fits["a"].starts]
    assert labels == [s["start"] for s in alone.starts]
    assert "reduced (Ch, Rih, Th0, pTh where they vanish)" in labels
