"""Scenario files: TOML, deep-merged over the defaults below, validated at the boundary.

A scenario is a nested dict with the sections ``scenario, site, launcher, flight, legs, wind,
gnss, imu, mag, earth, atmosphere, baro, airspeed, fc, faults, autopilot``; docs/SIMULATOR.md documents every key.
``load_scenario(name_or_path_or_dict, overrides)`` returns the merged, validated dict.
"""
from __future__ import annotations

import copy
import math
import pathlib
import tomllib
from typing import Any

SCENARIO_DIR = pathlib.Path(__file__).resolve().parent / "scenarios"

DEFAULTS: dict[str, Any] = {
    "scenario": {"name": "", "description": "", "duration_s": 300.0, "date": 2026.9},
    "site": {"lat_deg": None, "lon_deg": None, "alt_m": 0.0},
    "launcher": {
        "type": "rail",              # rail | tube | runway
        "azimuth_deg": 0.0,          # direction of the launch (flight axis heading), deg from true north
        "elevation_deg": 15.0,       # rail elevation; tube default 90; runway 0
        "roll_deg": 0.0,             # airframe roll on the launcher
        "rest_s": 30.0,              # at rest on the launcher before the launch
        "boost_accel_m_s2": 60.0,    # rail/tube: acceleration along the flight axis
        "boost_time_s": 0.4,
        "takeoff_accel_m_s2": 3.0,   # runway: ground-roll acceleration
        "rotate_airspeed_m_s": 16.0, # runway: lift-off speed
        "ground_pitch_deg": 0.0,     # runway: pitch of the airframe on its wheels
        "spinup_s": 0.0,             # the motors run this long before rest_s (vibration from then)
        "pickup_s": 4.0,             # hand: picked up this long before the throw
        "hand_sway_scale": 1.0,      # hand: the hand's sway and tremor, times this (0: held still)
        "liftoff_accel_m_s2": 2.0,   # multicopter/vtol: vertical acceleration at lift-off ...
        "climb_rate_m_s": 2.0,       # ... up to this climb rate ...
        "hover_alt_m": 10.0,         # ... braking into a hover at this height above the site ...
        "hover_s": 5.0,              # ... for this long, then the legs in forward flight
    },
    "flight": {
        "cruise_airspeed_m_s": 22.0,
        "alpha_deg": 3.0,            # angle of attack at cruise airspeed in level flight
        "max_bank_deg": 45.0,
        "bank_rate_deg_s": 45.0,
        "bank_tau_s": 0.4,
        "gamma_rate_deg_s": 20.0,    # flight-path-angle rate limit (pitch-over after a vertical launch too)
        "gamma_tau_s": 0.8,
        "max_accel_m_s2": 3.0,       # airspeed change limit after the boost
        "max_climb_m_s": 6.0,
        "max_sink_m_s": 5.0,
        "wind_capture_s": 2.0,       # after leaving the launcher the wind takes over within this time
        "gust_response_tau_s": 1.5,  # ground velocity follows gusts with this lag (airspeed sees the rest)
        "loiter_radius_m": 120.0,
        "heading_gain_1_s": 0.5,     # heading/course error -> turn-rate command
        "alt_gain_1_s": 0.3,         # altitude error -> climb-rate command
    },
    "legs": [],
    "motion": {"segments": []},      # launcher.type "rig": [{duration_s, by_deg = [droll, dpitch, dyaw], move_m?}]
    "wind": {"north_m_s": 0.0, "east_m_s": 0.0, "down_m_s": 0.0, "gust_sigma_m_s": 0.0, "gust_tau_s": 4.0},
    "gnss": {"lost_at_s": None},
    "imu": {"mount_euler_deg": [0.0, 0.0, 0.0]},
    "mag": {
        "hard_iron_gauss": [0.0, 0.0, 0.0],
        "soft_iron": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "site_distortion_ned_gauss": [0.0, 0.0, 0.0],
        "site_distortion_fade_m": 15.0,
        "anomalies": [],
        "disturbances": [],          # [{start_s, end_s?, field_ned_gauss | hard_iron_gauss}] (sim/sensors.py)
    },
    "earth": {                       # the simulator's Earth is not the estimators' WMM (sim/earth.py)
        "model_error": True,         # draw the WMM-2025 error budget per seed (IGRF-14 + the draw)
        "crustal_sigma_nt": 50.0,    # crustal anomaly field, 1 sigma of its vertical component
        "crustal_correlation_m": 2000.0,
    },
    "atmosphere": {                  # None: drawn per seed (sim/earth.py: draw_atmosphere)
        "qnh_hpa": None,             # sea-level pressure
        "isa_deviation_k": None,     # sea-level temperature minus ISA's 288.15 K
        "lapse_rate_k_km": None,     # temperature lapse rate (ISA: 6.5)
    },
    "baro": {"noise_pa": 2.0, "bias_pa": 0.0, "temperature_offset_k": 5.0, "temperature_noise_k": 0.05,
             "rate_hz": 50.0},
    "airspeed": {"noise_pa": 1.5, "offset_pa": 0.0},
    "vibration": {                   # motor vibration on the IMU from launcher.spinup_s before rest_s
        "accel_rms_m_s2": 0.0,       # per axis, at the blade-pass frequency
        "gyro_rms_rad_s": 0.0,       # per axis, same frequency
        "freq_hz": 137.0,            # blade-pass frequency (sampled as is: it aliases, as on an FC)
        "freq_wander_hz": 4.0,       # the motor speed's slow change (+-, period 7 s)
        "broadband_accel_rms_m_s2": 0.0,  # per axis, white
    },
    "fc": {
        "rate_hz": 50.0,             # offline fc_* arrays rate
        "roll_pitch_error_deg": 0.3, # 1-sigma, Gauss-Markov
        "yaw_error_deg": 1.0,
        "error_tau_s": 20.0,
        "degraded_tilt_error_deg": 2.0,
        "degraded_yaw_drift_deg_s": 0.05,
    },
    "faults": {
        "drop_rate": 0.0, "corrupt_rate": 0.0, "duplicate_rate": 0.0, "reorder_rate": 0.0,
        "nan_rate": 0.0,
        "outages": [],               # [[start_s, end_s], ...] no traffic either way
        "reboot_at_s": None,         # FC reboot: time_boot restarts, stream rates back to defaults
        "reboot_silence_s": 2.0,
        "sensor_dropouts": [],       # [{sensor = "mag"|"imu"|"baro"|"airspeed", start_s, end_s}]
    },
    "autopilot": {"personality": "ardupilot", "system_id": 1, "component_id": 1,
                  "base_rate_hz": 1000.0, "simstate_rate_hz": 10.0},
}

LAUNCHER_TYPES = ("rail", "tube", "runway", "hand", "multicopter", "vtol", "rig")
LEG_TYPES = ("climb", "descend", "level", "turn", "figure8", "loiter", "goto", "rtl")


def deep_merge(base: dict, over: dict | None) -> dict:
    """Return a copy of ``base`` with ``over`` merged in (dicts recursively, everything else replaced)."""
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def available_scenarios() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def read_scenario_source(scenario: str | pathlib.Path | dict) -> dict:
    if isinstance(scenario, dict):
        return copy.deepcopy(scenario)
    p = pathlib.Path(scenario)
    if not p.suffix and not p.exists():
        p = SCENARIO_DIR / f"{scenario}.toml"
    if not p.is_file():
        raise ValueError(f"scenario {str(scenario)!r} is neither a file nor one of {available_scenarios()}")
    with open(p, "rb") as f:
        try:
            return tomllib.load(f)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"scenario file {p}: {exc}") from exc


def _num(d: dict, sect: str, key: str, lo=-math.inf, hi=math.inf, allow_none=False, lo_open=False):
    v = d[sect][key]
    if v is None and allow_none:
        return
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{sect}.{key} must be a finite number, got {v!r}")
    if v < lo or v > hi or (lo_open and v == lo):
        raise ValueError(f"{sect}.{key} must be in {'(' if lo_open else '['}{lo}, {hi}], got {v}")
    d[sect][key] = float(v)


def _vec(d: dict, sect: str, key: str, n: int = 3):
    v = d[sect][key]
    try:
        ok = len(v) == n and all(isinstance(x, (int, float)) and math.isfinite(x) for x in v)
    except TypeError:
        ok = False
    if not ok:
        raise ValueError(f"{sect}.{key} must be a list of {n} finite numbers, got {v!r}")


def validate(s: dict) -> dict:
    """Validate a merged scenario in place (and return it). Raises ValueError naming the key."""
    unknown = set(s) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"unknown scenario section(s) {sorted(unknown)}; known: {sorted(DEFAULTS)}")
    for sect, dflt in DEFAULTS.items():
        if isinstance(dflt, dict) and sect != "imu":
            extra = set(s[sect]) - set(dflt)
            if extra:
                raise ValueError(f"unknown key(s) {sorted(extra)} in [{sect}]; known: {sorted(dflt)}")
    if s["site"]["lat_deg"] is None or s["site"]["lon_deg"] is None:
        raise ValueError("site.lat_deg and site.lon_deg are required (no hidden geographic default)")
    _num(s, "site", "lat_deg", -90.0, 90.0)
    _num(s, "site", "lon_deg", -180.0, 180.0)
    _num(s, "site", "alt_m", -400.0, 10000.0)
    _num(s, "scenario", "duration_s", 0.0, 86400.0, lo_open=True)
    from sim.earth import decimal_year_from_date
    s["scenario"]["decimal_year"] = decimal_year_from_date(s["scenario"]["date"])
    L = s["launcher"]
    if L["type"] not in LAUNCHER_TYPES:
        raise ValueError(f"launcher.type must be one of {LAUNCHER_TYPES}, got {L['type']!r}")
    _num(s, "launcher", "azimuth_deg", -360.0, 360.0)
    _num(s, "launcher", "elevation_deg", -10.0, 90.0)
    _num(s, "launcher", "roll_deg", -90.0, 90.0)
    _num(s, "launcher", "rest_s", 0.0, 86400.0)
    _num(s, "launcher", "boost_accel_m_s2", 0.0, 2000.0, lo_open=True)
    _num(s, "launcher", "boost_time_s", 0.0, 60.0, lo_open=True)
    _num(s, "launcher", "takeoff_accel_m_s2", 0.0, 50.0, lo_open=True)
    _num(s, "launcher", "rotate_airspeed_m_s", 0.0, 200.0, lo_open=True)
    _num(s, "launcher", "ground_pitch_deg", -20.0, 20.0)
    _num(s, "launcher", "spinup_s", 0.0, 86400.0)
    _num(s, "launcher", "pickup_s", 1.5, 600.0)
    _num(s, "launcher", "hand_sway_scale", 0.0, 10.0)
    _num(s, "launcher", "liftoff_accel_m_s2", 0.0, 20.0, lo_open=True)
    _num(s, "launcher", "climb_rate_m_s", 0.0, 20.0, lo_open=True)
    _num(s, "launcher", "hover_alt_m", 0.0, 1000.0, lo_open=True)
    _num(s, "launcher", "hover_s", 0.0, 86400.0)
    if L["type"] == "hand" and L["pickup_s"] > L["rest_s"]:
        raise ValueError(f"launcher.pickup_s ({L['pickup_s']}) must not exceed launcher.rest_s ({L['rest_s']})")
    for k in ("accel_rms_m_s2", "gyro_rms_rad_s", "freq_wander_hz", "broadband_accel_rms_m_s2"):
        _num(s, "vibration", k, 0.0, 1000.0)
    _num(s, "vibration", "freq_hz", 0.0, 5000.0, lo_open=True)
    F = s["flight"]
    for k in F:
        _num(s, "flight", k, 0.0, 1e6, lo_open=k not in ("alpha_deg",))
    _num(s, "flight", "alpha_deg", -10.0, 20.0)
    _num(s, "flight", "max_bank_deg", 0.0, 60.0, lo_open=True)
    for k in ("north_m_s", "east_m_s", "down_m_s"):
        _num(s, "wind", k, -100.0, 100.0)
    _num(s, "wind", "gust_sigma_m_s", 0.0, 50.0)
    _num(s, "wind", "gust_tau_s", 0.0, 1e4, lo_open=True)
    _num(s, "gnss", "lost_at_s", 0.0, 1e6, allow_none=True)
    _vec(s, "imu", "mount_euler_deg")
    _vec(s, "mag", "hard_iron_gauss")
    _vec(s, "mag", "site_distortion_ned_gauss")
    si = s["mag"]["soft_iron"]
    if not (isinstance(si, list) and len(si) == 3 and all(isinstance(r, list) and len(r) == 3 for r in si)):
        raise ValueError(f"mag.soft_iron must be a 3x3 list of lists, got {si!r}")
    _num(s, "mag", "site_distortion_fade_m", 0.0, 1e6, lo_open=True)
    for i, a in enumerate(s["mag"]["anomalies"]):
        for k in ("north_m", "east_m", "radius_m", "field_ned_gauss"):
            if k not in a:
                raise ValueError(f"mag.anomalies[{i}] needs key {k!r}")
    for i, d in enumerate(s["mag"]["disturbances"]):
        kinds = [k for k in ("field_ned_gauss", "hard_iron_gauss") if k in d]
        if not isinstance(d, dict) or len(kinds) != 1 or "start_s" not in d \
                or set(d) - {"start_s", "end_s", "field_ned_gauss", "hard_iron_gauss"}:
            raise ValueError(f"mag.disturbances[{i}] needs start_s, optional end_s and exactly one of "
                             f"field_ned_gauss (a magnet nearby) or hard_iron_gauss (a magnet attached); got {d!r}")
        if not (isinstance(d[kinds[0]], list) and len(d[kinds[0]]) == 3):
            raise ValueError(f"mag.disturbances[{i}].{kinds[0]} must be a list of 3 numbers (gauss)")
    segs = s["motion"]["segments"]
    for i, seg in enumerate(segs):
        if not isinstance(seg, dict) or not {"duration_s", "by_deg"} <= set(seg) <= {"duration_s", "by_deg", "move_m"} \
                or not (isinstance(seg["duration_s"], (int, float)) and seg["duration_s"] > 0
                        and isinstance(seg["by_deg"], list) and len(seg["by_deg"]) == 3
                        and len(seg.get("move_m", [0, 0, 0])) == 3):
            raise ValueError(f"motion.segments[{i}] needs duration_s > 0, by_deg = [droll, dpitch, dyaw] and "
                             f"optionally move_m = [dn, de, dd]; got {seg!r}")
    if segs and L["type"] != "rig":
        raise ValueError("motion.segments are only used with launcher.type = 'rig'")
    if not isinstance(s["earth"]["model_error"], bool):
        raise ValueError(f"earth.model_error must be true or false, got {s['earth']['model_error']!r}")
    _num(s, "earth", "crustal_sigma_nt", 0.0, 5000.0)
    _num(s, "earth", "crustal_correlation_m", 10.0, 1e6)
    _num(s, "atmosphere", "qnh_hpa", 850.0, 1100.0, allow_none=True)
    _num(s, "atmosphere", "isa_deviation_k", -60.0, 60.0, allow_none=True)
    _num(s, "atmosphere", "lapse_rate_k_km", 0.5, 9.8, allow_none=True)
    for k in ("noise_pa", "bias_pa", "temperature_offset_k", "temperature_noise_k"):
        _num(s, "baro", k, -1e5, 1e5)
    _num(s, "baro", "rate_hz", 0.0, 1000.0, lo_open=True)
    _num(s, "airspeed", "noise_pa", 0.0, 1e4)
    _num(s, "airspeed", "offset_pa", -1e4, 1e4)
    for k in s["fc"]:
        _num(s, "fc", k, 0.0, 1e6)
    for k in ("drop_rate", "corrupt_rate", "duplicate_rate", "reorder_rate", "nan_rate"):
        _num(s, "faults", k, 0.0, 1.0)
    _num(s, "faults", "reboot_at_s", 0.0, 1e6, allow_none=True)
    for w in s["faults"]["outages"]:
        if not (isinstance(w, list) and len(w) == 2 and w[0] <= w[1]):
            raise ValueError(f"faults.outages entries must be [start_s, end_s], got {w!r}")
    for d in s["faults"]["sensor_dropouts"]:
        if d.get("sensor") not in ("mag", "imu", "baro", "airspeed") or "start_s" not in d or "end_s" not in d:
            raise ValueError(f"faults.sensor_dropouts entries need sensor (mag|imu|baro|airspeed), start_s, end_s; got {d!r}")
    if s["autopilot"]["personality"] not in ("ardupilot", "px4"):
        raise ValueError(f"autopilot.personality must be 'ardupilot' or 'px4', got {s['autopilot']['personality']!r}")
    for i, leg in enumerate(s["legs"]):
        if not isinstance(leg, dict) or leg.get("type") not in LEG_TYPES:
            raise ValueError(f"legs[{i}].type must be one of {LEG_TYPES}, got {leg!r}")
    return s


def load_scenario(scenario: str | pathlib.Path | dict = "inclined_rail", overrides: dict | None = None) -> dict:
    """Defaults <- scenario file (name in sim/scenarios/, a path, or a dict) <- overrides; validated."""
    src = read_scenario_source(scenario)
    merged = deep_merge(deep_merge(DEFAULTS, src), overrides)
    if merged["launcher"]["type"] == "tube" and "elevation_deg" not in src.get("launcher", {}) \
            and "elevation_deg" not in (overrides or {}).get("launcher", {}):
        merged["launcher"]["elevation_deg"] = 90.0
    if merged["launcher"]["type"] == "runway":
        merged["launcher"]["elevation_deg"] = 0.0
    return validate(merged)
