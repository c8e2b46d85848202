"""The daemon's TOML configuration: one table of keys, validated at start.

Every key is declared once in ``SPEC`` with its type, default, valid range and a one-line doc; the
example config ``systemd/azimuthd.toml`` documents the same keys and a test keeps the two in step.
Errors name the key and the problem (``ConfigError: mavlink.imu_rate_hz: must be in (0, 1000],
got 5000``); unknown keys are errors too, so a typo never silently falls back to a default.
"""
from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

DEFAULT_CONFIG_PATH = "/etc/azimuthd/azimuthd.toml"


class ConfigError(ValueError):
    """A config file that cannot be used; the message names the key and the problem."""


@dataclass(frozen=True)
class Key:
    type: type | tuple
    default: Any
    doc: str
    check: Callable[[Any], str | None] | None = None
    """Returns None when the value is valid, else what is wrong."""


def _range(lo: float, hi: float, lo_open: bool = False, hi_open: bool = False):
    def check(v):
        if not math.isfinite(v):
            return f"must be finite, got {v}"
        ok_lo = v > lo if lo_open else v >= lo
        ok_hi = v < hi if hi_open else v <= hi
        if ok_lo and ok_hi:
            return None
        return f"must be in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}, got {v:g}"
    return check


def _choice(*options: str):
    def check(v):
        return None if v in options else f"must be one of {', '.join(options)}; got {v!r}"
    return check


def _mavlink_url(v: str, role: str = "fc"):
    from mavlink_io.url import parse_url
    try:
        parse_url(v, role)
    except ValueError as exc:
        return str(exc)
    return None


def _url_list(v: list):
    for i, item in enumerate(v):
        if not isinstance(item, str):
            return f"item {i} must be a string, got {type(item).__name__}"
        err = _mavlink_url(item, "out")
        if err:
            return f"item {i}: {err}"
    return None


def _str_list(v: list):
    for i, item in enumerate(v):
        if not isinstance(item, str):
            return f"item {i} must be a string, got {type(item).__name__}"
    return None


def _vehicle_name(v: str):
    if not 1 <= len(v) <= 32 or not all(c.isascii() and (c.isalnum() or c in "_-") for c in v):
        return f"must be 1..32 characters of A-Z a-z 0-9 _ -; got {v!r}"
    return None


def _field_vector(v: list):
    if len(v) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
        return f"must be three finite numbers [north, east, down] in gauss, got {v!r}"
    if not 0.05 <= math.sqrt(sum(x * x for x in v)) <= 1.0:
        return "magnitude must be 0.05..1.0 gauss (Earth's field is 0.22..0.67 G)"
    return None


_F = (int, float)

SPEC: dict[str, dict[str, Key]] = {
    "vehicle": {
        "name": Key(str, "uav1", "vehicle name in Zenoh keys azimuthd/<name>/... (1..32 of A-Z a-z 0-9 _ -)", _vehicle_name),
    },
    "mavlink": {
        "url": Key(str, "udpin:0.0.0.0:14550", "flight controller link (udpin:, udpout:, tcp:, tcpin:, serial:DEV:BAUD, /dev/tty...:BAUD)", _mavlink_url),
        "system_id": Key(int, 0, "vehicle system id; 0 = learn it from the autopilot's HEARTBEAT", _range(0, 255)),
        "component_id": Key(int, 191, "our component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)", _range(1, 255)),
        "heartbeat_hz": Key(_F, 1.0, "our HEARTBEAT rate", _range(0.2, 10)),
        "link_timeout_s": Key(_F, 2.0, "silence after which the link counts as lost and streams are re-requested", _range(0.2, 60)),
        "imu_gap_s": Key(_F, 0.5, "IMU sample interval reported as a gap (not integrated)", _range(0.005, 10)),
        "imu_rate_hz": Key(_F, 200.0, "requested RAW_IMU / HIGHRES_IMU rate", _range(1, 1000)),
        "pressure_rate_hz": Key(_F, 50.0, "requested SCALED_PRESSURE rate", _range(1, 200)),
        "attitude_rate_hz": Key(_F, 50.0, "requested rate of the FC's own ATTITUDE (reference for method B)", _range(1, 200)),
        "imu_batch": Key(bool, False, "hand a read's RAW_IMU frames to the estimators as one batch (off: one sample per message, the path flown longest; on saves no measured daemon CPU today)", None),
        "udp_rcvbuf_bytes": Key(int, 4 * 1024 * 1024, "UDP receive buffer asked for (the kernel caps it at net.core.rmem_max)", _range(65536, 256 * 1024 * 1024)),
        "signing_key_file": Key(str, "", "MAVLink 2 signing key file (64 hex characters or 32 bytes, mode 600); \"${CREDENTIALS_DIRECTORY}/NAME\" for a systemd LoadCredential=; \"\" = signing off", None),
        "sign_outgoing": Key(bool, True, "sign what we send (with a key)", None),
        "require_signed": Key(str, "commands", "with a key, which unsigned messages are refused: commands (commands to our component) | all | none", _choice("commands", "all", "none")),
        "accept_commands": Key(bool, True, "act on commands to our component (MAV_CMD_REQUEST_MESSAGE, MAV_CMD_DO_FENCE_ENABLE); false = deny them all", None),
    },
    "site": {
        "lat_deg": Key(_F, None, "launch site latitude (required unless earth_field_ned_gauss is set)", _range(-90, 90)),
        "lon_deg": Key(_F, None, "launch site longitude", _range(-180, 180)),
        "alt_m": Key(_F, 0.0, "launch site altitude above the WGS-84 ellipsoid", _range(-500, 10000)),
        "decimal_year": Key(_F, None, "date for the field model (e.g. 2026.9); default: today", _range(2025, 2030)),
        "earth_field_ned_gauss": Key(list, None, "the Earth field [N, E, D] in gauss, instead of the WMM", _field_vector),
    },
    "imu": {
        "mount_roll_deg": Key(_F, 0.0, "IMU mounting: roll of the sensor axes in the body frame", _range(-180, 180)),
        "mount_pitch_deg": Key(_F, 0.0, "IMU mounting: pitch of the sensor axes in the body frame", _range(-90, 90)),
        "mount_yaw_deg": Key(_F, 0.0, "IMU mounting: yaw of the sensor axes in the body frame", _range(-180, 180)),
        "still_seconds": Key(_F, 2.0, "at-rest data needed for levelling and gyro bias", _range(0.2, 600)),
        "accel_bias_sigma_m_s2": Key(_F, 0.1, "1-sigma accelerometer bias after the FC's calibration (tilt error ~ bias/g; 0.1 = 10 mg = 0.58 deg). The FC calibrates the offset at one temperature; what it leaves is the offset's temperature coefficient times the warming since: 0.5 mg/K (x, y) and 1 mg/K (z) for an ICM-20602 over 10-20 K, 0.15 mg/K for an ICM-42688-P over 68 K", _range(0, 5)),
        "gyro_bias_sigma_deg_s": Key(_F, 0.01, "1-sigma gyro bias left after the at-rest estimate (in-run drift + Earth rate): the at-rest mean holds Earth rate (15.04 deg/h = 0.0042 deg/s), wrong by up to twice that once the airframe turns, plus a consumer MEMS gyro's in-run bias instability (a few deg/h)", _range(0, 10)),
    },
    "launch": {
        "case": Key(str, "inclined", "how the flight direction is found: vertical | inclined | aligned", _choice("vertical", "inclined", "aligned")),
        "vehicle": Key(str, "auto", "how the vehicle takes off: auto (from the FC's HEARTBEAT type and take-off parameters, service/vehicle_type.py) | launcher (rail/tube/catapult boost) | hand (a throw) | runway (a take-off roll) | multicopter | vtol (a vertical lift-off)", _choice("auto", "launcher", "hand", "runway", "multicopter", "vtol")),
        "detect_accel_m_s2": Key(_F, 5.0, "launch when |specific force| exceeds g by this much ...", _range(0.3, 200)),
        "detect_hold_s": Key(_F, 0.05, "... for this long", _range(0.0, 5)),
        "boost_window_s": Key(_F, 1.0, "time after launch used for the flight direction (inclined case)", _range(0.05, 10)),
        "in_flight_start_detect": Key(bool, True, "a daemon (re)started while the FC is armed and flying does not level or wait for a launch (airspeed, baro rate, motion, specific force)", None),
        "in_flight_airspeed_m_s": Key(_F, 12.0, "... airspeed that means flying; set it above the strongest wind on the launcher", _range(3, 80)),
        "in_flight_alt_rate_m_s": Key(_F, 1.5, "... |baro altitude rate| that means flying", _range(0.3, 30)),
    },
    "azimuth": {
        "distortion_model": Key(str, "full12", "magnetometer distortion model: full12 (3x3 soft + hard iron) | seed7 (the seed's 3 scales, 3 biases)", _choice("seed7", "full12")),
        "solve_in_background": Key(bool, True, "run the least-squares re-solves in a worker process (the daemon); false = inline", None),
    },
    "ahrs": {
        "variant": Key(str, "b2", "synthetic AHRS (method B): b2 computes the heading (KF1 + KF2), b1 takes it from the other sources", _choice("b1", "b2")),
    },
    "heading": {
        "min_horizontal_field_gauss": Key(_F, 0.03, "below this horizontal field the magnetometer heading is declared unavailable (method C)", _range(0.0, 0.5)),
        "cruise_speed_m_s": Key(_F, 25.0, "typical ground speed, for the transport-rate allowance of the heading filter near the poles", _range(0, 400)),
        "manoeuvre_speed_m_s": Key(_F, 0.0, "speed along the nose (m/s) with which method C's attitude filter bounds the centripetal acceleration of a turn when no airspeed is measured (a fixed wing's measured true airspeed is used whenever the air data has one; a multicopter's differential pressure is no airspeed); 0 = the vehicle's: 25 for a multicopter (it also accelerates sideways), cruise_speed_m_s for a fixed wing. Set it for a vehicle slower than that, e.g. a hand-carried IMU (~1.5)", _range(0, 400)),
        "filter_rate_hz": Key(_F, 50.0, "rate of the attitude/heading filters and of the NavSolution (the IMU is integrated at its full rate)", _range(5, 1000)),
        "uncalibrated_hard_iron_gauss": Key(_F, 0.016, "per-axis 1-sigma of the magnetometer hard iron nobody has compensated yet (before method D's coefficients apply): widens the heading filter's sigma. 0.016 G: ArduPilot's compass calibration accepts a fit whose RMS residual is up to COMPASS_CAL_FIT = 16 mGauss (its default; MAG_CAL_REPORT.fitness), and RAW_IMU carries that residual", _range(0.0, 0.5)),
        "uncalibrated_soft_iron": Key(_F, 0.0175, "per-element 1-sigma of the soft iron the magnetometer's compensation leaves, equally the per-axis misalignment (rad) of its axes against the IMU's (the same heading variance, estimators/polar_heading.py): widens the heading filter's sigma. 0.0175 = 1 deg: an ellipsoid compass calibration cannot see a rotation of the magnetometer's axes; OpenPilot measured 1-2 deg between a magnetometer and its accelerometer. 0 for a magnetometer compensated and aligned (method D, a lab calibration)", _range(0.0, 0.5)),
        "mag_heading_floor_deg": Key(_F, 1.0, "1-sigma floor of each magnetometer heading measurement of method C: the heading errors no model here covers (deviation left after a compensation, an anomaly beyond the WMM's error model, time skew between magnetometer and IMU), counted once per 30 s of correlation like the declination and tilt errors. Tuned: no datasheet or measurement gives it; it keeps C's sigma 2-3x its error on compensated simulated flights (docs/SIGMAS.md)", _range(0.0, 10.0, lo_open=True)),
        "fc_yaw_sigma_deg": Key(_F, 1.5, "1-sigma error of the FC's own yaw while trusted (its reading in the fusion and what method B copies from it). Measured on ArduPilot's own EKF3 in ArduPlane SITL (bench/ardupilot_sitl.py, 4 flights): 0.6 deg RMS with GNSS, 1.6-1.9 deg in the 80 s after a GNSS cut; 1.5 covers the seconds before the loss is seen", _range(0.1, 20)),
        "use_fc_when_trusted": Key(bool, True, "fuse the FC's own yaw while its estimator is trusted (GNSS healthy, agrees with our gyros)", None),
        "use_fc_yaw": Key(bool, True, "false: the FC's yaw is used nowhere (not a heading source, not method B's reference yaw or magnetometer-calibration reference); its roll/pitch may still be used", None),
    },
    "deviation": {
        "calibrate": Key(bool, False, "fit the magnetometer deviation model (method D) in flight, while a trusted heading exists: fly a calibration manoeuvre", None),
        "apply": Key(bool, True, "correct the magnetometer of the heading filter with the stored deviation coefficients", None),
        "min_coverage": Key(_F, 0.5, "apply the coefficients only when the manoeuvre covered this fraction of heading/roll/pitch bins", _range(0, 1)),
    },
    "outputs": {
        "attitude_hz": Key(_F, 50.0, "ATTITUDE / ATTITUDE_QUATERNION rate we send", _range(1, 400)),
        "odometry_hz": Key(_F, 10.0, "ODOMETRY (heading feed to the FC's EKF) rate, only while heading is valid", _range(5, 100)),
        "named_value_hz": Key(_F, 2.0, "NAMED_VALUE_FLOAT (azimuth, heading sigma, phase) rate", _range(0.1, 50)),
        "extra_mavlink_urls": Key(list, [], "more MAVLink endpoints that get our outputs (a GCS, a test client)", _url_list),
        "status_interval_s": Key(_F, 0.0, "print a status line to stdout this often; 0 = never", _range(0, 3600)),
        "max_tilt_sigma_deg": Key(_F, 10.0, "roll/pitch 1-sigma above which no attitude (ATTITUDE, quaternion, ODOMETRY) is sent", _range(0.1, 90)),
        "max_heading_sigma_deg": Key(_F, 15.0, "heading 1-sigma above which no heading is sent (ATTITUDE yaw NaN, no quaternion, no ODOMETRY)", _range(0.1, 180)),
        "max_extrapolation_s": Key(_F, 0.15, "outputs go at their rates whatever the IMU rate: the last solution brought forward by its body rates, up to this age; older, nothing is sent", _range(0.001, 2)),
        "attitude_to_fc": Key(bool, True, "send ATTITUDE / ATTITUDE_QUATERNION to the FC link too (ArduPilot forwards them to every port: ground stations see the FC's attitude and ours, components 1 and 191); false: only ODOMETRY, NAMED_VALUE_FLOAT, HEARTBEAT go to the FC, extra_mavlink_urls always get everything", None),
    },
    "zenoh": {
        "enabled": Key(bool, True, "publish state over Zenoh", None),
        "mode": Key(str, "peer", "Zenoh session mode: peer | client", _choice("peer", "client")),
        "listen": Key(list, [], "Zenoh listen endpoints, e.g. tcp/127.0.0.1:7447", _str_list),
        "connect": Key(list, [], "Zenoh endpoints to connect to (a router)", _str_list),
        "tls_root_ca": Key(str, "", "TLS root CA file for tls/ endpoints", None),
        "tls_cert": Key(str, "", "TLS certificate file", None),
        "tls_key": Key(str, "", "TLS private key file", None),
    },
    "service": {
        "state_dir": Key(str, "", "calibrations live here; default $STATE_DIRECTORY, else ~/.local/state/azimuthd", None),
        "log_level": Key(str, "info", "debug | info | warning | error", _choice("debug", "info", "warning", "error")),
    },
}


NESTED_SECTIONS = ("geofence",)
"""Sections with nested values (polygons, action lists), validated by their own module."""


def _type_ok(value: Any, typ: type | tuple) -> bool:
    if isinstance(value, bool) and typ is not bool:
        return False  # TOML true is not a number
    return isinstance(value, typ)


def _type_name(typ: type | tuple) -> str:
    if typ == _F:
        return "a number"
    return {str: "a string", int: "an integer", bool: "true or false", list: "a list"}.get(typ, str(typ))


def validate(raw: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Check a parsed TOML document against SPEC; returns every key with defaults filled in."""
    out: dict[str, dict[str, Any]] = {}
    for section in raw:
        if section not in SPEC and section not in NESTED_SECTIONS:
            raise ConfigError(f"{section}: unknown section (known: {', '.join([*SPEC, *NESTED_SECTIONS])})")
        if not isinstance(raw[section], dict):
            raise ConfigError(f"{section}: must be a table [{section}]")
    for section, keys in SPEC.items():
        given = raw.get(section, {})
        for key in given:
            if key not in keys:
                raise ConfigError(f"{section}.{key}: unknown key (known: {', '.join(keys)})")
        values = {}
        for key, spec in keys.items():
            name = f"{section}.{key}"
            if key not in given:
                values[key] = spec.default
                continue
            v = given[key]
            if not _type_ok(v, spec.type):
                raise ConfigError(f"{name}: must be {_type_name(spec.type)}, got {v!r}")
            if spec.type == _F:
                v = float(v)
            if spec.check is not None:
                problem = spec.check(v)
                if problem:
                    raise ConfigError(f"{name}: {problem}")
            values[key] = v
        out[section] = values
    from service.geofence_config import validate_geofence  # polygons and actions: its own validator
    out["geofence"] = validate_geofence(raw.get("geofence"))
    if out["geofence"] is not None and out["site"]["lat_deg"] is None:
        raise ConfigError("site.lat_deg: the geofence needs the launch site (lat_deg, lon_deg)")
    site = out["site"]
    if (site["lat_deg"] is None) != (site["lon_deg"] is None):
        raise ConfigError("site.lon_deg: lat_deg and lon_deg go together")
    if site["earth_field_ned_gauss"] is None and site["lat_deg"] is None:
        raise ConfigError("site.lat_deg: required: the launch site is not set; set [site] lat_deg and lon_deg "
                          "(or earth_field_ned_gauss) in the config (no default: a wrong site gives a wrong heading)")
    return out


def load(path: str | os.PathLike) -> dict[str, dict[str, Any]]:
    """Read and validate a config file; ConfigError names the file and the problem."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return validate(raw)


def state_dir(cfg: dict[str, dict[str, Any]]) -> Path:
    """The directory for calibrations: config, else systemd's $STATE_DIRECTORY, else per-user."""
    if cfg["service"]["state_dir"]:
        return Path(cfg["service"]["state_dir"])
    sd = os.environ.get("STATE_DIRECTORY")
    if sd:
        return Path(sd.split(":")[0])
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "azimuthd"
