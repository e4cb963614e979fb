"""greyid.datasets.fetch: the mirror's files, and a download checked against its SHA-256."""

from __future__ import annotations

import hashlib
import http.server
import json
import shutil
import subprocess
import threading
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import greyid
import greyid.data.named as fetching
from test_crosscheck import DATA

SHAPES = {"armadillo": (233, 5), "ornstein_1d": (201, 3), "ornstein_2d": (201, 4), "prbs1": (1691, 5),
          "theophylline": (132, 5), "annex58_ce4_1min": (5760, 46), "annex58_ce4_10min": (528, 56)}


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_every_data_set_reads_from_the_mirror(name, monkeypatch):
    if not (DATA / fetching.SOURCES[name].mirror).is_file():
        pytest.skip(f"the mirror {DATA} has no {fetching.SOURCES[name].mirror}")
    monkeypatch.setenv(fetching.MIRROR, str(DATA))
    frame = fetching.fetch(name)
    assert frame.shape == SHAPES[name]


def test_an_unknown_name_and_a_missing_mirror_file_are_named(monkeypatch, tmp_path):
    with pytest.raises(greyid.DataError, match="no data set named 'armadilo'.*armadillo"):
        fetching.fetch("armadilo")
    monkeypatch.setenv(fetching.MIRROR, str(tmp_path))
    with pytest.raises(greyid.DataError, match=r"put the file armadillo_data_H2.csv from https://\S+ in it"):
        fetching.fetch("armadillo")


def test_a_plain_folder_of_the_sources_files_serves_as_the_mirror(monkeypatch, tmp_path):
    """What a user has without the network: the files as their sources serve them, side by side."""
    if not (DATA / fetching.SOURCES["armadillo"].mirror).is_file():
        pytest.skip(f"the mirror {DATA} has no Armadillo file")
    shutil.copy(DATA / fetching.SOURCES["armadillo"].mirror, tmp_path / fetching.source_file("armadillo"))
    monkeypatch.setenv(fetching.MIRROR, str(tmp_path))
    assert fetching.fetch("armadillo").shape == SHAPES["armadillo"]


def test_an_offline_download_says_which_file_to_put_where(server, tmp_path, monkeypatch):
    """No network (here: a port nobody listens on): no HTTP library's message, but the file and the variable."""
    pytest.importorskip("pooch")
    _, url = server
    closed = url.rsplit(":", 1)[0] + ":9"  # the discard port: refused
    monkeypatch.delenv(fetching.MIRROR, raising=False)
    source = fetching.Source(f"{closed}/houses/data.csv", "0" * 64, "none/data.csv", fetching._read_csv(),
                             fetching._read_csv(), "test", "test")
    monkeypatch.setitem(fetching.SOURCES, "local", source)
    with pytest.raises(greyid.DataError) as refused:
        fetching.fetch("local", data_home=tmp_path / "cache")
    message = str(refused.value)
    assert "could not be downloaded" in message and "put data.csv in a folder and set GREYID_DATA_MIRROR" in message
    assert "urllib3" not in message and "HTTPConnection" not in message and "Max retries" not in message


def test_the_data_guide_lists_every_data_set_with_its_file():
    guide = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "data.md").read_text(encoding="utf-8")
    for name, source in fetching.SOURCES.items():
        row = next((line for line in guide.splitlines() if line.startswith(f"| `{name}` ")), None)
        assert row is not None, name
        assert f"`{fetching.source_file(name)}`" in row and f"`{source.mirror}`" in row, row


@pytest.fixture
def server(tmp_path):
    """A local HTTP server of tmp_path/served (no network needed)."""
    served = tmp_path / "served"
    served.mkdir()
    handler = partial(http.server.SimpleHTTPRequestHandler, directory=str(served))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield served, f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()


def test_a_download_is_checked_against_its_sha256(server, tmp_path, monkeypatch):
    pytest.importorskip("pooch")
    served, url = server
    text = "t,y\n0,1.5\n1,2.5\n"
    (served / "data.csv").write_text(text)
    digest = hashlib.sha256(text.encode()).hexdigest()
    monkeypatch.delenv(fetching.MIRROR, raising=False)
    source = fetching.Source(f"{url}/data.csv", digest, "none.csv", fetching._read_csv(), fetching._read_csv(),
                             "test", "test")
    monkeypatch.setitem(fetching.SOURCES, "local", source)
    frame = fetching.fetch("local", data_home=tmp_path / "cache")
    pd.testing.assert_frame_equal(frame, pd.DataFrame({"t": [0, 1], "y": [1.5, 2.5]}))
    monkeypatch.setitem(fetching.SOURCES, "local", fetching.Source(f"{url}/data.csv", "0" * 64, "none.csv",
                                                                   fetching._read_csv(), fetching._read_csv(),
                                                                   "test", "test"))
    with pytest.raises(greyid.DataError, match="does not match its SHA-256"):
        fetching.fetch("local", data_home=tmp_path / "other")


def test_the_annex58_ten_minute_data_are_derived_as_the_course_derives_them():
    """The course's 10-minute file (the mirror's) from its 1-minute series by greyid's port of its R code."""
    from greyid.data.annex58 import ten_minutes

    minutes, course = DATA / "annex58_test_box" / "ce4_1min.csv", DATA / "annex58_test_box" / "ce4_10min.csv"
    if not (minutes.is_file() and course.is_file()):
        pytest.skip(f"the mirror {DATA} has no Annex 58 files")
    derived, expected = ten_minutes(pd.read_csv(minutes)), pd.read_csv(course)
    assert list(derived.columns) == list(expected.columns) and len(derived) == len(expected) == 528
    assert (derived["timedate"].dt.strftime("%Y-%m-%d %H:%M:%S") == expected["timedate"]).all()
    for column in expected.columns.drop("timedate"):
        a, b = derived[column].to_numpy(float), expected[column].to_numpy(float)
        assert np.array_equal(np.isnan(a), np.isnan(b)), column  # a period with a gap is missing in both
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10, equal_nan=True, err_msg=column)


def test_the_course_rda_time_column_reads_as_utc_timestamps(tmp_path):
    """X5.rda's POSIXct column becomes timestamps (an .rda written by R, where R is installed)."""
    pytest.importorskip("rdata")
    if shutil.which("Rscript") is None:
        pytest.skip("R is not installed: no .rda can be written here")
    from greyid.data.annex58 import read_x5

    path = tmp_path / "X.rda"
    script = (f'X <- data.frame(t = as.POSIXct(c("2013-06-28 00:00:00", "2013-06-28 00:01:00"), tz = "UTC"), '
              f'Qi = c(1.5, NA)); save(X, file = "{path}")')
    subprocess.run(["Rscript", "-e", script], check=True, capture_output=True)
    frame = read_x5(path)
    assert list(frame["t"]) == [pd.Timestamp("2013-06-28 00:00:00"), pd.Timestamp("2013-06-28 00:01:00")]
    assert frame["Qi"].iloc[0] == 1.5 and np.isnan(frame["Qi"].iloc[1])


def test_a_model_file_names_its_data_set_and_a_saved_fit_keeps_it(tmp_path, monkeypatch):
    """[data] dataset = "armadillo": `greyid fit` reads it, fit.json keeps "dataset:armadillo", and
    `greyid fit fit.json` and `greyid validate fit.json` find the same data again."""
    from greyid.cli import main

    if not (DATA / fetching.SOURCES["armadillo"].mirror).is_file():
        pytest.skip(f"the mirror {DATA} has no Armadillo file")
    monkeypatch.setenv(fetching.MIRROR, str(DATA))
    model_file = Path(__file__).resolve().parents[1] / "examples" / "armadillo.toml"
    assert main(["fit", str(model_file), "--out", str(tmp_path / "first"), "-q"]) == 0
    saved = json.loads((tmp_path / "first" / "fit.json").read_text())
    assert saved["data_file"] == "dataset:armadillo"
    assert main(["fit", str(tmp_path / "first" / "fit.json"), "--out", str(tmp_path / "again"), "-q"]) == 0
    again = json.loads((tmp_path / "again" / "fit.json").read_text())
    assert again["data_file"] == "dataset:armadillo"
    assert abs(again["loglik"] - saved["loglik"]) < 1e-6
    assert main(["validate", str(tmp_path / "first" / "fit.json")]) in (0, 1)  # a verdict, not bad input (2)
    both = model_file.read_text().replace('dataset = "armadillo"', 'dataset = "armadillo"\nfile = "x.csv"')
    (tmp_path / "both.toml").write_text(both)
    assert main(["fit", str(tmp_path / "both.toml"), "-q"]) == 2
    with pytest.raises(greyid.DataError, match="both a data file .* and a data set"):
        from greyid.model.files import read_data

        read_data(greyid.Model.from_toml(tmp_path / "both.toml"))


def test_without_pooch_the_command_line_says_what_to_install(tmp_path, monkeypatch, capsys):
    """A data set named in a model file, no mirror and no pooch: exit 2 and the pip command, no traceback."""
    import sys

    from greyid.cli import main

    monkeypatch.delenv(fetching.MIRROR, raising=False)
    monkeypatch.setitem(sys.modules, "pooch", None)  # import pooch raises ImportError
    model_file = Path(__file__).resolve().parents[1] / "examples" / "armadillo.toml"
    assert main(["fit", str(model_file), "-q"]) == 2
    err = capsys.readouterr().err
    assert 'pip install "greyid[data]"' in err and "Traceback" not in err
