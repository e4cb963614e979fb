"""Solar radiation on a tilted surface as model inputs (section 7.4), computed with pvlib.

A window or wall is modelled with the beam (direct) and diffuse radiation on
its plane and the angle of incidence of the beam, θ_inc in (7.52)–(7.54).  The
astronomy (solar position) and the transposition of horizontal measurements to
the surface are pvlib's, the library of the solar-energy field.

The direct transmittance of glazing as a function of θ_inc is the model
function ``glazing_transmittance(theta, N)`` in equations
([`greyid.model.physics`][greyid.model.physics]).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..errors import DataError, ModelError

def solar_inputs(times, latitude: float, longitude: float, tilt: float, azimuth: float, ghi=None, dni=None,
                 dhi=None, altitude: float = 0.0, diffuse_model: str = "isotropic") -> pd.DataFrame:
    """Angle of incidence and the beam/diffuse split on a surface, per timestamp.

    ``times``: timestamps with a time zone (a ``DatetimeIndex`` or a Series of
    them).  ``tilt`` from the horizontal (90 for a wall) and ``azimuth`` of the
    surface's normal (degrees east of north: 180 faces south).  Radiation
    measured on the horizontal: ``ghi`` (global) alone, split into beam and
    diffuse by Erbs' correlation, or ``dni`` (beam normal) with ``dhi``
    (diffuse horizontal), in W/m².  ``diffuse_model`` is pvlib's sky model
    ("isotropic", "haydavies", "perez" ...).  Returns a DataFrame on ``times``
    with ``incidence`` (degrees; above 90 the sun is behind the surface),
    ``incidence_rad``, ``cos_incidence`` (0 when behind), ``solar_elevation``
    (degrees) and, with radiation given, ``beam`` and ``diffuse`` on the
    surface (W/m², ground reflection in ``diffuse``) and ``global`` their sum.
    """
    try:
        import pvlib
    except ImportError:
        raise ModelError('solar geometry needs pvlib: pip install "greyid[solar]"') from None
    index = pd.DatetimeIndex(times)
    if index.tz is None:
        raise DataError("the timestamps have no time zone; solar geometry needs it (e.g. "
                        "pd.to_datetime(...).tz_localize('Europe/Copenhagen') or utc=True)")
    if not -90 <= latitude <= 90 or not -180 <= longitude <= 180:
        raise DataError(f"latitude must lie in [-90, 90] and longitude in [-180, 180], got {latitude}, {longitude}")
    if not 0 <= tilt <= 180:
        raise DataError(f"tilt must lie in [0, 180] degrees from the horizontal, got {tilt}")
    position = pvlib.solarposition.get_solarposition(index, latitude, longitude, altitude=altitude)
    zenith, sun_azimuth = position["apparent_zenith"], position["azimuth"]
    incidence = pvlib.irradiance.aoi(tilt, azimuth, zenith, sun_azimuth)
    out = pd.DataFrame({"incidence": incidence.to_numpy(), "incidence_rad": np.radians(incidence.to_numpy()),
                        "cos_incidence": np.clip(np.cos(np.radians(incidence.to_numpy())), 0.0, None),
                        "solar_elevation": position["apparent_elevation"].to_numpy()}, index=index)
    if ghi is None and dni is None:
        return out
    if ghi is not None and dni is None:
        ghi = pd.Series(np.asarray(ghi, dtype=np.float64), index=index)
        split = pvlib.irradiance.erbs(ghi, zenith, index)
        dni, dhi = split["dni"], split["dhi"]
    elif dni is None or dhi is None:
        raise DataError("give ghi alone, or dni with dhi (and optionally ghi)")
    dni = pd.Series(np.asarray(dni, dtype=np.float64), index=index)
    dhi = pd.Series(np.asarray(dhi, dtype=np.float64), index=index)
    if ghi is None:
        ghi = dhi + dni * np.clip(np.cos(np.radians(zenith)), 0.0, None)
    ghi = pd.Series(np.asarray(ghi, dtype=np.float64), index=index)
    for name, series in (("ghi", ghi), ("dni", dni), ("dhi", dhi)):
        bad = np.flatnonzero(~np.isfinite(series.to_numpy()) | (series.to_numpy() < 0))
        if bad.size:
            raise DataError(f"{name} must be finite and non-negative; row {bad[0]} holds {series.iloc[bad[0]]!r}")
    extra = {}
    if diffuse_model in ("haydavies", "reindl", "perez"):
        extra["dni_extra"] = pvlib.irradiance.get_extra_radiation(index)
    if diffuse_model == "perez":
        extra["airmass"] = pvlib.atmosphere.get_relative_airmass(zenith)
    plane = pvlib.irradiance.get_total_irradiance(tilt, azimuth, zenith, sun_azimuth, dni, ghi, dhi,
                                                  model=diffuse_model, **extra)
    out["beam"] = plane["poa_direct"].fillna(0.0).clip(lower=0.0).to_numpy()
    out["diffuse"] = plane["poa_diffuse"].fillna(0.0).to_numpy()
    out["global"] = out["beam"] + out["diffuse"]
    return out
