"""greyid.datasets.fetch: the mirror's files, and a download checked against its SHA-256."""

from __future__ import annotations

import hashlib
import http.server
import threading
from functools import partial

import pandas as pd
import pytest

import greyid
import greyid.datasets.remote as fetching
from test_crosscheck import DATA

SHAPES = {"armadillo": (233, 5), "ornstein_1d": (201, 3), "ornstein_2d": (201, 4), "prbs1": (1691, 5),
          "theophylline": (132, 5)}


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
    with pytest.raises(greyid.DataError, match="not found in the mirror"):
        fetching.fetch("armadillo")


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
