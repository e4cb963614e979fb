"""Outputs survive faults: atomic files, a folder as one generation, output paths checked first."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from greyid.outputs import JOURNAL, complete_generation, write_atomic, write_generation

ROOT = Path(__file__).resolve().parents[1]


def test_write_atomic_leaves_the_old_file_whole_when_the_write_fails(tmp_path, monkeypatch):
    target = tmp_path / "fit.json"
    target.write_text("old")

    def broken(source, destination):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken)
    with pytest.raises(OSError):
        write_atomic(target, "new")
    monkeypatch.undo()
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.json"]  # no temporary left


def test_a_generation_is_all_new_or_all_old(tmp_path, monkeypatch):
    folder = tmp_path / "out"
    write_generation(folder, {"fit.json": "1", "summary.txt": "1", "parameters.csv": "1"})
    # Killed while writing the new files (before the journal): the old generation stays.
    calls = {"n": 0}
    real_write = Path.write_bytes

    import greyid.outputs as outputs

    real_new = outputs._write_new

    def dies_on_second(path, blob):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        real_new(path, blob)

    monkeypatch.setattr(outputs, "_write_new", dies_on_second)
    with pytest.raises(KeyboardInterrupt):
        write_generation(folder, {"fit.json": "2", "summary.txt": "2", "parameters.csv": "2"})
    monkeypatch.undo()
    complete_generation(folder)
    assert {p.name: p.read_text() for p in folder.iterdir()} == {"fit.json": "1", "summary.txt": "1",
                                                                 "parameters.csv": "1"}
    # Killed while moving them into place (after the journal): the next reader completes it.
    real_replace = os.replace
    moved = {"n": 0}

    def dies_after_first_move(source, destination):
        if str(destination).endswith(JOURNAL):
            return real_replace(source, destination)
        moved["n"] += 1
        if moved["n"] == 2:
            raise KeyboardInterrupt
        return real_replace(source, destination)

    monkeypatch.setattr(os, "replace", dies_after_first_move)
    with pytest.raises(KeyboardInterrupt):
        write_generation(folder, {"fit.json": "3", "summary.txt": "3", "parameters.csv": "3"})
    monkeypatch.undo()
    assert (folder / JOURNAL).exists()
    complete_generation(folder)
    assert {p.name: p.read_text() for p in folder.iterdir()} == {"fit.json": "3", "summary.txt": "3",
                                                                 "parameters.csv": "3"}
    del real_write


SLOW_FIT = """
import os, sys, time
real = os.replace
def slow(source, destination):  # a slowed write: the process is killed in the middle
    if not str(destination).endswith('.greyid-generation.json'):
        time.sleep(1.0)
    return real(source, destination)
os.replace = slow
from greyid.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_killed_fit_leaves_one_generation(tmp_path):
    """`greyid fit --out DIR` killed while moving its files into place: DIR then holds the previous
    run's files or (once any greyid command reads it) the new run's, never a mixture."""
    data = ROOT / "src" / "greyid" / "datasets"
    model = data / "building.toml"
    out = tmp_path / "out"
    env = dict(os.environ, GREYID_CACHE_DIR=str(tmp_path / "cache"))
    first = subprocess.run([sys.executable, "-m", "greyid", "fit", str(model), "--out", str(out), "-q"],
                           env=env, capture_output=True, text=True)
    assert first.returncode in (0, 1), first.stderr
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # A second run of other data (the first 500 rows): its files differ from the first run's.
    import pandas as pd

    frame = pd.read_csv(data / "building.csv").iloc[:500]
    short = tmp_path / "short.csv"
    frame.to_csv(short, index=False)
    process = subprocess.Popen([sys.executable, "-c", SLOW_FIT, "fit", str(model), str(short), "--out", str(out),
                                "-q"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not (out / JOURNAL).exists() and time.time() < deadline and process.poll() is None:
        time.sleep(0.02)
    assert (out / JOURNAL).exists(), "the run reached its moves"
    time.sleep(0.3)
    process.send_signal(signal.SIGKILL)
    process.wait()
    # The previous fit is whole in the folder, or the journal completes the new one.
    assert json.loads((out / "fit.json").read_text()) is not None
    shown = subprocess.run([sys.executable, "-m", "greyid", "validate", str(out / "fit.json")], env=env,
                           capture_output=True, text=True)
    assert shown.returncode in (0, 1), shown.stderr
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(after) == set(before)
    fit = json.loads(after["fit.json"])
    summary = after["summary.txt"].decode()
    assert f"observations: {fit['n_obs']}" in summary  # fit.json and summary.txt of the same run
    assert fit["n_obs"] == 500 and after != before


def test_output_paths_are_refused_before_any_work(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    loop = tmp_path / "loop"
    os.symlink(tmp_path / "loop2", loop)
    os.symlink(loop, tmp_path / "loop2")
    model = ROOT / "src" / "greyid" / "datasets" / "building.toml"
    for out, words in ((afile / "x", "is a file"), (afile, "is a file"), (Path("/proc/greyid-out"), "cannot write"),
                       (loop / "x", "leads nowhere")):
        started = time.time()
        result = subprocess.run([sys.executable, "-m", "greyid", "fit", str(model), "--out", str(out), "-q"],
                                capture_output=True, text=True)
        assert result.returncode == 2 and words in result.stderr and "Traceback" not in result.stderr, result.stderr
        assert time.time() - started < 30  # refused before fitting
    for out in (afile / "x.csv", tmp_path / "missing" / "x.csv"):
        result = subprocess.run([sys.executable, "-m", "greyid", "simulate", str(model), "--out", str(out)],
                                capture_output=True, text=True)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
