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


def _generation(folder: Path) -> dict:
    """The folder's files as one reader sees them: listed and read through one open handle of the folder."""
    handle = os.open(folder, os.O_RDONLY)
    try:
        files = {}
        for name in os.listdir(handle):
            with open(os.open(name, os.O_RDONLY, dir_fd=handle)) as file:
                files[name] = file.read()
        return files
    finally:
        os.close(handle)


def test_a_killed_write_leaves_the_old_generation_and_a_users_files_stay(tmp_path, monkeypatch):
    import greyid.outputs as outputs

    folder = tmp_path / "out"
    write_generation(folder, {"fit.json": "1", "summary.txt": "1", "parameters.csv": "1"})
    (folder / "notes.txt").write_text("mine")
    calls = {"n": 0}
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
    assert _generation(folder) == {"fit.json": "1", "summary.txt": "1", "parameters.csv": "1", "notes.txt": "mine"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it
    write_generation(folder, {"fit.json": "3", "summary.txt": "3"})
    assert _generation(folder) == {"fit.json": "3", "summary.txt": "3", "parameters.csv": "1", "notes.txt": "mine"}


def test_a_file_where_the_folder_should_be_is_left_alone(tmp_path):
    afile = tmp_path / "out"
    afile.write_text("mine")
    with pytest.raises(NotADirectoryError, match="is a file"):
        write_generation(afile, {"fit.json": "1"})
    assert afile.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_reader_sees_one_whole_generation_at_every_moment(tmp_path, monkeypatch):
    """While a generation is written (each file slowed), the folder read over and over shows the old
    files or the new ones, never some of each nor a file missing."""
    import threading

    import greyid.outputs as outputs

    folder = tmp_path / "out"
    names = ("fit.json", "summary.txt", "parameters.csv", "report.html")
    write_generation(folder, {n: "1" for n in names})
    real_new = outputs._write_new

    def slow(path, blob):
        time.sleep(0.05)
        real_new(path, blob)

    monkeypatch.setattr(outputs, "_write_new", slow)
    writer = threading.Thread(target=lambda: [write_generation(folder, {n: str(g) for n in names})
                                              for g in (2, 3, 4)])
    writer.start()
    seen = set()
    while writer.is_alive():
        state = _generation(folder)
        assert set(state) == set(names), state
        assert len(set(state.values())) == 1, state
        seen.add(next(iter(state.values())))
    writer.join()
    assert _generation(folder) == {n: "4" for n in names}
    assert len(seen) >= 2  # the reader did see the folder change


def test_a_reader_that_opened_the_folder_before_an_exchange_reads_the_whole_previous_generation(tmp_path):
    """The retired generation stays until the next write exchanges its own: a reader holding the folder
    open across one write still reads every file of the generation it opened; one more write removes it."""
    folder = tmp_path / "out"
    names = ("fit.json", "summary.txt")
    write_generation(folder, {n: "1" for n in names})
    handle = os.open(folder, os.O_RDONLY)
    try:
        write_generation(folder, {n: "2" for n in names})
        assert _generation(folder) == {n: "2" for n in names}
        for name in names:
            with open(os.open(name, os.O_RDONLY, dir_fd=handle)) as file:
                assert file.read() == "1"
        write_generation(folder, {n: "3" for n in names})
        assert os.listdir(handle) == []  # the generation two writes back is gone
    finally:
        os.close(handle)
    hidden = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert len(hidden) == 1 and {p.name: p.read_text() for p in (tmp_path / hidden[0]).iterdir()} == {
        n: "2" for n in names}


def test_without_folder_exchange_the_journal_completes_a_generation(tmp_path, monkeypatch):
    """Where folders cannot be exchanged (another system), the files move behind a journal that the
    next reader or writer carries out."""
    import greyid.outputs as outputs

    monkeypatch.setattr(outputs, "_exchange", lambda first, second: False)
    folder = tmp_path / "out"
    write_generation(folder, {"fit.json": "1", "summary.txt": "1"})
    write_generation(folder, {"fit.json": "2", "summary.txt": "2"})
    assert _generation(folder) == {"fit.json": "2", "summary.txt": "2"}
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
        write_generation(folder, {"fit.json": "3", "summary.txt": "3"})
    monkeypatch.setattr(os, "replace", real_replace)
    assert (folder / JOURNAL).exists()
    complete_generation(folder)
    assert _generation(folder) == {"fit.json": "3", "summary.txt": "3"}


def test_the_folder_exchange_is_used_on_linux(tmp_path):
    from greyid.outputs import _exchange

    if not sys.platform.startswith("linux"):
        pytest.skip("renameat2 is Linux's")
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "x").write_text("a")
    (b / "x").write_text("b")
    assert _exchange(a, b)
    assert (a / "x").read_text() == "b" and (b / "x").read_text() == "a"


SLOW_FIT = """
import sys, time
import greyid.outputs as outputs
real = outputs._write_new
def slow(path, blob):  # a slowed write: the process is killed in the middle of the files
    time.sleep(0.4)
    open(sys.argv[-1], 'a').close()
    real(path, blob)
outputs._write_new = slow
from greyid.cli import main
sys.exit(main(sys.argv[1:-1]))
"""


@pytest.mark.slow
def test_a_killed_fit_leaves_one_generation(tmp_path):
    """`greyid fit --out DIR` killed while it writes its files: DIR holds the previous run's files, whole,
    as anyone who opens it sees them (no greyid command needs to read it first), and a later run
    leaves nothing of the killed one behind."""
    data = ROOT / "src" / "greyid" / "datasets"
    model = data / "building.toml"
    out = tmp_path / "out"
    env = dict(os.environ, GREYID_CACHE_DIR=str(tmp_path / "cache"))
    first = subprocess.run([sys.executable, "-m", "greyid", "fit", str(model), "--out", str(out), "-q"],
                           env=env, capture_output=True, text=True)
    assert first.returncode in (0, 1), first.stderr
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    import pandas as pd

    frame = pd.read_csv(data / "building.csv").iloc[:500]
    short = tmp_path / "short.csv"
    frame.to_csv(short, index=False)
    writing = tmp_path / "writing"
    process = subprocess.Popen([sys.executable, "-c", SLOW_FIT, "fit", str(model), str(short), "--out", str(out),
                                "-q", str(writing)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not writing.exists() and time.time() < deadline and process.poll() is None:
        time.sleep(0.02)
    assert writing.exists(), "the run reached its writes"
    time.sleep(0.6)  # inside the second file's write
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    again = subprocess.run([sys.executable, "-m", "greyid", "fit", str(model), str(short), "--out", str(out), "-q"],
                           env=env, capture_output=True, text=True)
    assert again.returncode in (0, 1), again.stderr
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(after) == set(before) and after != before
    fit = json.loads(after["fit.json"])
    assert fit["n_obs"] == 500 and f"observations: {fit['n_obs']}" in after["summary.txt"].decode()
    # No leftover of the killed run: only the generation the last write retired, kept for its readers
    hidden = [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert [p.name.split(".")[-2] for p in hidden] == ["retired"]
    assert {p.name: p.read_bytes() for p in hidden[0].iterdir()} == before


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
