"""R data files (.rda) as data frames, through the ``rdata`` package (no R needed)."""

import warnings

import pandas as pd

from ..errors import DataError


def read_rda(path) -> pd.DataFrame:
    """The one data frame of an R .rda file (the ``rdata`` package: no R needed)."""
    try:
        import rdata
    except ImportError:
        raise ImportError('reading R data files needs rdata: pip install "greyid[data]"') from None

    with warnings.catch_warnings():  # POSIXct has no constructor in rdata: its seconds are what is wanted
        warnings.filterwarnings("ignore", message="Missing constructor for R class", category=UserWarning)
        frames = rdata.read_rda(str(path))
    if len(frames) != 1:
        raise DataError(f"'{path}' holds {len(frames)} R objects; one data frame was expected")
    frame = next(iter(frames.values()))
    frame.columns = [str(c) for c in frame.columns]
    return frame.reset_index(drop=True)
