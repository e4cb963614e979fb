"""Real data sets by name, from their original public sources, checked by SHA-256.

    from greyid.datasets import fetch
    frame = fetch("armadillo")

Each data set is downloaded once (pooch) from the repository and file its
provenance names, verified against the SHA-256 kept here, cached in the user's
cache folder (``pooch.os_cache("greyid")``) and read into a DataFrame.  The
environment variable ``GREYID_DATA_MIRROR`` names a local folder to read instead,
with nothing downloaded: a plain folder of the files as their sources serve them,
or a mirror laid out as the table of the data guide shows (each data set's CSV in
its own sub-folder; tests and CI use one).  The data are not greyid's: their
licences are in ``SOURCES``.

Downloading needs the ``data`` extra (``pip install "greyid[data]"``: pooch, and
rdata for R's .rda files); the mirror needs neither.  The Annex 58 test box's 10-minute data are derived
from the course's 1-minute .rda as the course's R code derives them
([`greyid.data.annex58`][greyid.data.annex58]).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from ..errors import DataError
from .rda import read_rda

MIRROR = "GREYID_DATA_MIRROR"


def _read_csv(sep: str = ",", parse: list[str] | None = None):
    def read(path):
        frame = pd.read_csv(path, sep=sep)
        for column in parse or []:
            frame[column] = pd.to_datetime(frame[column])
        return frame

    return read


def _r_vector(text: str) -> list[str]:
    return [v.strip().strip('"') for v in text.replace("\n", " ").split(",") if v.strip()]


def _read_r_dump(path) -> pd.DataFrame:
    """R's ``datasets/data/Theoph.R``: a ``structure(list(...))`` of numeric columns and one ordered factor."""
    text = Path(path).read_text(encoding="utf-8")
    columns = {}
    for name, body in re.findall(r"(\w+)\s*=\s*c\(([^()]*)\)", text):
        if name in ("Wt", "Dose", "Time", "conc"):
            columns[name] = np.array(_r_vector(body), dtype=float)
    factor = re.search(r"Subject\s*=\s*ordered\(c\(([^()]*)\),\s*levels\s*=\s*1:(\d+),\s*labels\s*=\s*c\(([^()]*)\)",
                       text)
    if factor is None or set(columns) != {"Wt", "Dose", "Time", "conc"}:
        raise DataError(f"'{path}' is not R's Theoph data set as expected")
    codes = np.array(_r_vector(factor.group(1)), dtype=int)
    labels = _r_vector(factor.group(3))
    frame = pd.DataFrame({"Subject": [int(labels[c - 1]) for c in codes], **columns})
    return frame[["Subject", "Wt", "Dose", "Time", "conc"]]


@dataclass(frozen=True)
class Source:
    """Where a data set comes from and how it is read."""

    url: str
    sha256: str
    mirror: str  # its file in a folder laid out like shared/data
    read: Callable  # the downloaded file → DataFrame
    read_mirror: Callable  # the mirror's file → DataFrame
    licence: str
    description: str


def _annex58_minutes(path) -> pd.DataFrame:
    from .annex58 import read_x5

    return read_x5(path)


def _annex58_ten_minutes(path) -> pd.DataFrame:
    from .annex58 import read_x5, ten_minutes

    return ten_minutes(read_x5(path))


GITHUB = "https://raw.githubusercontent.com"
EXERCISES = f"{GITHUB}/marcohv/exercises_ts_dtu/1d1d6ad6b7285b0019ab0151f116e1030a073555"
X5_SHA256 = "fb84ac3c61d80a0fa74e09de44e4b5f99e7d59d0936ba2488aaf877f18fc6d15"
SOURCES: dict[str, Source] = {
    "armadillo": Source(
        f"{GITHUB}/locie/pySIP/da70d25619add47e6d16b75d95a662d2630f5547/data/armadillo/armadillo_data_H2.csv",
        "87cafaf39e414a4f732c4ed01c8c74cc69c3cbad43ab439e68a40f39b9236a16",
        "armadillo_box/armadillo_data_H2.csv", _read_csv(), _read_csv(),
        "pySIP's repository (LGPL-3 in early versions, MIT in later documentation)",
        "The Armadillo Box (42 m², Solar Decathlon 2010): 233 rows every 1800 s; Time [s], T_ext [°C], "
        "P_hea [W], I_sol [W/m²], T_int [°C]."),
    "ornstein_1d": Source(
        f"{GITHUB}/phillipbvetter/ctsmTMB/60590a51d725c53edb58a9733bde24245aa67716/data/Ornstein.rda",
        "a0a5a8dc094d14c2b2f96dfdc08ace4a547c97dedfb3ecc948d60d1b8347690a",
        "ornstein_uhlenbeck/ornstein_1d.csv", read_rda, _read_csv(), "ctsmTMB (GPL-3)",
        "A simulated Ornstein–Uhlenbeck process: t (0 to 20 by 0.1), input u, observation y."),
    "ornstein_2d": Source(
        f"{GITHUB}/phillipbvetter/ctsmTMB/60590a51d725c53edb58a9733bde24245aa67716/data/Ornstein2D.rda",
        "e5f7fb262f64d432158be29c8437aa74081626a414a12ba0c8ec5611e89dde9a",
        "ornstein_uhlenbeck/ornstein_2d.csv", read_rda, _read_csv(), "ctsmTMB (GPL-3)",
        "A simulated two-state Ornstein–Uhlenbeck system: t, u, y1, y2."),
    "prbs1": Source(
        f"{EXERCISES}/Ex_2/inputPRBS1.csv",
        "0934b179efdee4874b8f93c22d5e9258483425a7353de5f8623c69a72f7e70f5",
        "prbs1_test_house/inputPRBS1.csv", _read_csv(";"), _read_csv(";"), "no licence stated",
        "Bacher & Madsen's (2011) PRBS1 experiment: 1691 five-minute averages; t [h], Ta [°C], Ps [kW/m²], "
        "Ph [kW], yTi [°C]."),
    "theophylline": Source(
        f"{GITHUB}/wch/r-source/02e4ee85542c87153eab3bed860fdd6ffd9920be/src/library/datasets/data/Theoph.R",
        "36fafc4b23e7551bb596a7068b391cddc9d6aa725738d43c011bdbf3e60e7bdb",
        "theophylline/Theoph.csv", _read_r_dump, _read_csv(), "distributed with R under the GPL",
        "Boeckmann, Sheiner & Beal (1994): 12 subjects, 11 concentrations each; Subject, Wt [kg], Dose [mg/kg], "
        "Time [h], conc [mg/L]."),
    "annex58_ce4_1min": Source(
        f"{EXERCISES}/Ex_3/data/X5.rda", X5_SHA256, "annex58_test_box/ce4_1min.csv", _annex58_minutes,
        _read_csv(parse=["t"]), "no licence stated",
        "IEA EBC Annex 58 Common Exercise 4 (a test box with a glazed wall, summer 2013), as the DTU course's "
        "Ex_3 gives it: 5760 one-minute rows from 2013-06-28 00:00 UTC, 46 columns; t [timestamp, UTC], Ti.down "
        "and Ti.up [°C] (indoor air), Te.down and Te.middle [°C] (exterior), Qi [W] (heat input), Gv [W/m²] "
        "(vertical solar irradiance), Gvn.2 and the surface temperatures."),
    "annex58_ce4_10min": Source(
        f"{EXERCISES}/Ex_3/data/X5.rda", X5_SHA256, "annex58_test_box/ce4_10min.csv", _annex58_ten_minutes,
        _read_csv(parse=["timedate"]), "no licence stated",
        "The course exercise's 10-minute data, derived from the 1-minute series as its R code does "
        "(greyid.data.annex58.ten_minutes): 528 rows from 2013-06-28 08:10 UTC, t [s from the first "
        "sample], yTi = Ti [°C] (output), Te [°C], Gv [W/m²], Qi [W], stepQi, tod [h], sun position [rad]."),
}


def source_file(name: str) -> str:
    """The file name of data set ``name`` at its source (the last part of its address)."""
    return SOURCES[name].url.rsplit("/", 1)[-1]


def _from_mirror(name: str, mirror: str) -> pd.DataFrame:
    """The data set from a local folder: the mirror's layout, the mirror's file alone, or the source's file."""
    source, folder = SOURCES[name], Path(mirror)
    places = [(folder / source.mirror, source.read_mirror), (folder / Path(source.mirror).name, source.read_mirror),
              (folder / source_file(name), source.read)]
    for path, read in places:
        if path.is_file():
            return read(path)
    raise DataError(f"data set '{name}' is not in the folder {MIRROR}={mirror}: put the file "
                    f"{source_file(name)} from {source.url} in it (or the mirror's {Path(source.mirror).name} "
                    f"at {folder / source.mirror})")


def fetch(name: str, data_home=None) -> pd.DataFrame:
    """A real data set by name, as a DataFrame.

    Parameters
    ----------
    name : str
        One of the names in ``greyid.datasets.SOURCES``: ``"armadillo"``,
        ``"prbs1"``, ``"ornstein_1d"``, ``"ornstein_2d"``, ``"theophylline"``,
        ``"annex58_ce4_1min"``, ``"annex58_ce4_10min"``.
    data_home : str or pathlib.Path, optional
        Where downloads are kept (default: the user's cache folder,
        ``pooch.os_cache("greyid")``).

    Returns
    -------
    pandas.DataFrame
        The data set's columns as its description in ``SOURCES`` gives them.

    Raises
    ------
    DataError
        An unknown name; a file not found in the folder ``GREYID_DATA_MIRROR`` names
        (the message says which file to put there); a download that failed or whose
        SHA-256 differs from the one kept here.
    ImportError
        Downloading needs pooch (``pip install "greyid[data]"``).

    Notes
    -----
    Where the environment variable ``GREYID_DATA_MIRROR`` names a folder, nothing is
    downloaded: the data set is read from that folder, which may hold either the file
    as its source serves it (``armadillo_data_H2.csv``, ``Ornstein.rda``, ...: see the
    table in the data guide) or the mirror's CSV file, alone or in the mirror's
    sub-folder (``armadillo_box/armadillo_data_H2.csv``).

    Examples
    --------
    >>> import greyid
    >>> frame = greyid.datasets.fetch("armadillo")  # doctest: +SKIP
    >>> list(frame.columns)  # doctest: +SKIP
    ['Time', 'T_ext', 'P_hea', 'I_sol', 'T_int']
    """
    if name not in SOURCES:
        raise DataError(f"no data set named '{name}'; the data sets are {', '.join(SOURCES)}")
    source = SOURCES[name]
    mirror = os.environ.get(MIRROR)
    if mirror:
        return _from_mirror(name, mirror)
    try:
        import pooch
    except ImportError:
        raise ImportError(f'downloading data sets needs pooch: pip install "greyid[data]" (or put '
                          f"{source_file(name)} from {source.url} in a folder and set {MIRROR} to it)") from None
    offline = (f"without the network, download {source.url} elsewhere, put {source_file(name)} in a folder and set "
               f"{MIRROR} to that folder")
    try:
        path = pooch.retrieve(source.url, known_hash=f"sha256:{source.sha256}",
                              path=data_home or pooch.os_cache("greyid"), progressbar=False)
    except ValueError as error:  # pooch: the file's hash is not the one kept here
        raise DataError(f"data set '{name}' downloaded from {source.url} does not match its SHA-256 "
                        f"({error})") from None
    except OSError as error:
        raise DataError(f"data set '{name}' could not be downloaded from {source.url} "
                        f"({_short_reason(error)}); {offline}") from None
    return source.read(path)


def _short_reason(error: OSError) -> str:
    """What went wrong with a download, in a few words instead of the HTTP library's nested message."""
    text = str(error)
    for words, said in (("Name or service not known", "the host could not be found: no network?"),
                        ("Temporary failure in name resolution", "the host could not be found: no network?"),
                        ("Failed to resolve", "the host could not be found: no network?"),
                        ("Connection refused", "the connection was refused"),
                        ("timed out", "the connection timed out"),
                        ("Max retries exceeded", "no connection: no network?"),
                        ("404", "the file is not at that address (HTTP 404)")):
        if words in text:
            return said
    return type(error).__name__
