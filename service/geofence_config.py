"""The ``[geofence]`` config section: keys, defaults, validation (docs/GEOFENCE.md lists them all).

``validate_geofence(raw)`` takes the parsed ``[geofence]`` table (or None when the file has none)
and returns a frozen :class:`GeofenceConfig`, or None when the section is absent or
``enabled = false``. Errors are ``service.config.ConfigError("geofence.<key>: <problem>")``;
unknown keys are errors. The section is validated even when disabled (a typo never hides).

Geometry: the allowed area is the INTERSECTION of every inclusion polygon (and the azimuth
corridor, which is one more inclusion polygon built around the launch site), minus every
exclusion polygon; heights are relative to the launch site (``site.alt_m``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimators.geodesy import LocalGnomonic, polygon_is_simple
from service.config import ConfigError

ACTIONS = ("rtl", "rtl_mode", "loiter_mode", "reposition", "terminate")
WIND_SOURCES = ("config", "estimate")

_F = (int, float)

# key: (type, default, doc)
KEYS: dict[str, tuple[Any, Any, str]] = {
    "enabled": (bool, False, "run the geofence monitor"),
    "inclusion": (list, [], "inclusion polygons: a list of polygons, each a list of [lat_deg, lon_deg] (>= 3 vertices); the vehicle must stay inside all of them"),
    "exclusion": (list, [], "exclusion polygons, same form; the vehicle must stay outside each"),
    "alt_min_m": (_F, None, "minimum height above the launch site (m); unset = none"),
    "alt_max_m": (_F, None, "maximum height above the launch site (m); unset = none"),
    "corridor_azimuth_deg": (_F, None, "allowed azimuth corridor: centre bearing from the launch site (true, deg); unset = none"),
    "corridor_half_width_deg": (_F, 30.0, "corridor half width (deg), 1..179"),
    "corridor_range_m": (_F, 10000.0, "corridor length from the launch site (m)"),
    "corridor_home_radius_m": (_F, 300.0, "allowed disc around the launch site joined to the corridor (m)"),
    "margin_m": (_F, 50.0, "horizontal margin kept from the fence (m)"),
    "alt_margin_m": (_F, 10.0, "vertical margin kept from the height limits (m)"),
    "sigma_k": (_F, 2.0, "divert when the fence is within margin + sigma_k x the position sigma toward it"),
    "lookahead_s": (_F, 30.0, "breach prediction look-ahead along the current track (s)"),
    "trigger_hold_s": (_F, 0.5, "a predicted breach must persist this long before the divert (s)"),
    "clear_distance_m": (_F, 200.0, "the latch clears only when the clearance (after margin and uncertainty) exceeds this (m) ..."),
    "clear_hold_s": (_F, 10.0, "... with no breach predicted, for this long (s)"),
    "actions": (list, ["rtl"], f"ordered actions: the first on a breach, the next when one fails or the vehicle stays outside; any of {', '.join(ACTIONS)}"),
    "allow_termination": (bool, False, "explicit opt-in required for the 'terminate' action"),
    "safe_lat_deg": (_F, None, "safe point for 'reposition' (deg)"),
    "safe_lon_deg": (_F, None, "safe point for 'reposition' (deg)"),
    "safe_alt_m": (_F, 100.0, "safe point height above the launch site (m)"),
    "escalate_after_s": (_F, 30.0, "after an accepted action, the next one is sent if the estimated position is still outside after this long (s)"),
    "command_timeout_s": (_F, 1.0, "COMMAND_ACK wait per try (s)"),
    "command_tries": (int, 5, "tries per command before it counts as failed"),
    "wind_source": (str, "estimate", "config | estimate (from the FC's ground velocity while GNSS is healthy; config until then)"),
    "wind_north_m_s": (_F, 0.0, "configured wind, north component (blowing toward)"),
    "wind_east_m_s": (_F, 0.0, "configured wind, east component"),
    "wind_sigma_m_s": (_F, 3.0, "1-sigma of the configured wind per component (m/s)"),
    "wind_sigma_min_m_s": (_F, 0.5, "floor of the estimated wind's sigma (m/s)"),
    "tas_sigma_m_s": (_F, 1.0, "1-sigma true-airspeed error (calibration, density) (m/s)"),
    "fix_sigma_m": (_F, 5.0, "1-sigma of the FC's position at the last trusted fix, or of the launch site (m)"),
    "alt_sigma_m": (_F, 5.0, "1-sigma barometric height error (m)"),
    "heading_sigma_max_deg": (_F, 30.0, "a heading with a larger sigma counts as unknown (deg)"),
    "max_airspeed_m_s": (_F, 40.0, "upper bound on the airspeed while heading or airspeed is unknown (m/s)"),
    "update_hz": (_F, 10.0, "monitor update rate (Hz)"),
    "require_armed": (bool, True, "act only while the FC reports armed (and in flight)"),
}


@dataclass(frozen=True)
class GeofenceConfig:
    inclusion: tuple
    """Polygons, each a tuple of (lat_deg, lon_deg)."""
    exclusion: tuple
    alt_min_m: float | None
    alt_max_m: float | None
    corridor_azimuth_deg: float | None
    corridor_half_width_deg: float
    corridor_range_m: float
    corridor_home_radius_m: float
    margin_m: float
    alt_margin_m: float
    sigma_k: float
    lookahead_s: float
    trigger_hold_s: float
    clear_distance_m: float
    clear_hold_s: float
    actions: tuple
    allow_termination: bool
    safe_lat_deg: float | None
    safe_lon_deg: float | None
    safe_alt_m: float
    escalate_after_s: float
    command_timeout_s: float
    command_tries: int
    wind_source: str
    wind_north_m_s: float
    wind_east_m_s: float
    wind_sigma_m_s: float
    wind_sigma_min_m_s: float
    tas_sigma_m_s: float
    fix_sigma_m: float
    alt_sigma_m: float
    heading_sigma_max_deg: float
    max_airspeed_m_s: float
    update_hz: float
    require_armed: bool


_RANGES = {
    "alt_min_m": (-1000, 20000), "alt_max_m": (-1000, 20000), "corridor_azimuth_deg": (0, 360),
    "corridor_half_width_deg": (1, 179), "corridor_range_m": (100, 1e6), "corridor_home_radius_m": (10, 1e5),
    "margin_m": (0, 1e5), "alt_margin_m": (0, 1e4), "sigma_k": (0, 10), "lookahead_s": (1, 600),
    "trigger_hold_s": (0, 60), "clear_distance_m": (0, 1e5), "clear_hold_s": (0, 3600),
    "safe_lat_deg": (-90, 90), "safe_lon_deg": (-180, 180), "safe_alt_m": (-1000, 20000),
    "escalate_after_s": (1, 3600), "command_timeout_s": (0.05, 60), "command_tries": (1, 20),
    "wind_north_m_s": (-100, 100), "wind_east_m_s": (-100, 100), "wind_sigma_m_s": (0, 50),
    "wind_sigma_min_m_s": (0, 50), "tas_sigma_m_s": (0, 50), "fix_sigma_m": (0, 10000), "alt_sigma_m": (0, 1000),
    "heading_sigma_max_deg": (0.1, 180), "max_airspeed_m_s": (1, 400), "update_hz": (0.5, 100),
}


def _err(key: str, problem: str) -> ConfigError:
    return ConfigError(f"geofence.{key}: {problem}")


def _type_ok(v, typ) -> bool:
    if isinstance(v, bool) and typ is not bool:
        return False
    return isinstance(v, typ)


def _polygons(key: str, value: list) -> tuple:
    polys = []
    for i, poly in enumerate(value):
        where = f"polygon {i}"
        if not isinstance(poly, list) or len(poly) < 3:
            raise _err(key, f"{where} must be a list of at least 3 [lat_deg, lon_deg] vertices, got {poly!r}")
        verts = []
        for j, v in enumerate(poly):
            if (not isinstance(v, list) or len(v) != 2
                    or not all(_type_ok(x, _F) and math.isfinite(x) for x in v)):
                raise _err(key, f"{where} vertex {j} must be [lat_deg, lon_deg] (two finite numbers), got {v!r}")
            lat, lon = float(v[0]), float(v[1])
            if not -90 <= lat <= 90:
                raise _err(key, f"{where} vertex {j}: latitude must be in [-90, 90], got {lat:g}")
            if not -180 <= lon <= 180:
                raise _err(key, f"{where} vertex {j}: longitude must be in [-180, 180], got {lon:g}")
            verts.append((lat, lon))
        if verts[0] == verts[-1]:
            verts = verts[:-1]  # a closed ring written with the first vertex repeated
            if len(verts) < 3:
                raise _err(key, f"{where} has fewer than 3 distinct vertices")
        arr = np.radians(np.array(verts))
        centre = arr.mean(axis=0)
        try:
            plane = LocalGnomonic(float(centre[0]), float(math.atan2(np.sin(arr[:, 1]).mean(), np.cos(arr[:, 1]).mean())))
            xy = plane.forward(arr[:, 0], arr[:, 1])
        except ValueError:
            raise _err(key, f"{where} spans more than 2000 km: a fence must be local") from None
        if len({(round(x, 3), round(y, 3)) for x, y in xy}) != len(xy):
            raise _err(key, f"{where} has repeated vertices")
        if not polygon_is_simple(xy):
            raise _err(key, f"{where} crosses itself: the edges must not intersect")
        area = 0.5 * float(np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]))
        if abs(area) < 100.0:
            raise _err(key, f"{where} has (almost) no area ({abs(area):.1f} m^2)")
        polys.append(tuple(verts))
    return tuple(polys)


def validate_geofence(raw: dict | None) -> GeofenceConfig | None:
    """Validate the ``[geofence]`` table; None when absent or disabled (still validated)."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise ConfigError("geofence: must be a table [geofence]")
    for key in raw:
        if key not in KEYS:
            raise _err(key, f"unknown key (known: {', '.join(KEYS)})")
    vals: dict[str, Any] = {}
    for key, (typ, default, _doc) in KEYS.items():
        if key not in raw:
            vals[key] = list(default) if isinstance(default, list) else default
            continue
        v = raw[key]
        if not _type_ok(v, typ):
            tname = {bool: "true or false", list: "a list", str: "a string", int: "an integer"}.get(typ, "a number")
            raise _err(key, f"must be {tname}, got {v!r}")
        if typ == _F:
            v = float(v)
            if not math.isfinite(v):
                raise _err(key, f"must be finite, got {v}")
        if key in _RANGES:
            lo, hi = _RANGES[key]
            if not lo <= v <= hi:
                raise _err(key, f"must be in [{lo:g}, {hi:g}], got {v:g}")
        vals[key] = v
    vals["inclusion"] = _polygons("inclusion", vals["inclusion"])
    vals["exclusion"] = _polygons("exclusion", vals["exclusion"])
    if vals["wind_source"] not in WIND_SOURCES:
        raise _err("wind_source", f"must be one of {', '.join(WIND_SOURCES)}; got {vals['wind_source']!r}")
    acts = vals["actions"]
    if not acts:
        raise _err("actions", "must list at least one action")
    for i, a in enumerate(acts):
        if a not in ACTIONS:
            raise _err("actions", f"item {i} must be one of {', '.join(ACTIONS)}; got {a!r}")
    if len(set(acts)) != len(acts):
        raise _err("actions", f"lists an action twice: {acts!r}")
    if "terminate" in acts and not vals["allow_termination"]:
        raise _err("actions", "'terminate' needs the explicit opt-in geofence.allow_termination = true")
    if "terminate" in acts and acts[-1] != "terminate":
        raise _err("actions", "'terminate' can only be the last action")
    if "reposition" in acts and (vals["safe_lat_deg"] is None or vals["safe_lon_deg"] is None):
        raise _err("safe_lat_deg", "'reposition' needs safe_lat_deg and safe_lon_deg")
    if (vals["safe_lat_deg"] is None) != (vals["safe_lon_deg"] is None):
        raise _err("safe_lon_deg", "safe_lat_deg and safe_lon_deg go together")
    if vals["alt_min_m"] is not None and vals["alt_max_m"] is not None \
            and vals["alt_max_m"] - vals["alt_min_m"] <= 2 * vals["alt_margin_m"]:
        raise _err("alt_max_m", f"must exceed alt_min_m by more than 2 x alt_margin_m, got "
                                f"{vals['alt_min_m']:g}..{vals['alt_max_m']:g} with margin {vals['alt_margin_m']:g}")
    if vals["corridor_home_radius_m"] >= vals["corridor_range_m"]:
        raise _err("corridor_home_radius_m", "must be smaller than corridor_range_m")
    if not vals["enabled"]:
        return None
    if not (vals["inclusion"] or vals["exclusion"] or vals["alt_min_m"] is not None
            or vals["alt_max_m"] is not None or vals["corridor_azimuth_deg"] is not None):
        raise _err("enabled", "the geofence is enabled but defines no limit (inclusion, exclusion, "
                              "alt_min_m, alt_max_m or corridor_azimuth_deg)")
    vals["actions"] = tuple(acts)
    del vals["enabled"]
    return GeofenceConfig(**vals)


__all__ = ["GeofenceConfig", "validate_geofence", "KEYS", "ACTIONS"]
