"""Zenoh publisher: the daemon's state for dashboards, on ``azimuthd/<vehicle>/<topic>``.

Topics (service/schema/azimuthd.schema.json has every field): attitude, heading, azimuth,
air_data, calibration, geofence, health, events. Payloads are JSON objects (UTF-8, encoding
application/json) with ``schema`` = "azimuthd/1", ``vehicle``, ``time_unix_s`` (wall clock at
publication: the only clock two machines share) and units in the field names; non-finite
numbers become null. A liveliness token ``azimuthd/<vehicle>/alive`` exists while the
bus is open: subscribers see it appear, and disappear on ``close()`` or when the process dies
(the transport lease expires).

Never blocks the daemon: every publisher uses congestion control DROP (a slow or absent
subscriber loses samples, the daemon never waits), state topics at DATA priority, events and
calibration at DATA_HIGH so they go first when the link is busy. ``put`` failures are counted
in ``stats`` and never raised.

Default network set-up (works on one machine with no router, tested on loopback): peer mode,
multicast scouting off, listen on ``tcp/127.0.0.1:7447``. ``azimuthd watch`` connects to that
endpoint. For a ground station over a radio/IP link, listen on the vehicle's address or connect
to a router (client mode); TLS with ``tls/HOST:PORT`` endpoints and the ``tls`` dict.

The daemon calls:
    bus = ZenohBus(cfg["vehicle"]["name"], z["mode"], z["listen"], z["connect"], tls)
    bus.publish_solution(sol, now_s)           # every NavSolution; rate-limited per topic
    bus.publish("health", health_payload(...)) # ~1 Hz
    bus.publish("events", event_payload("launch_detected", "info", "..."))
    bus.publish("air_data", air_data_payload(air, time_rx_s))   # ~2 Hz
    bus.publish("calibration", calibration_payload("levelling", "done", "...", time_rx_s, ...))
    bus.close()
"""
from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from service.aiding import AidingRecord, payload as aiding_payload
from service.schema import SCHEMA_VERSION, TOPICS

if TYPE_CHECKING:
    from mavlink_io.navsolution import NavSolution

log = logging.getLogger("azimuthd.zenoh")

KEY_PREFIX = "azimuthd"
DEFAULT_LISTEN = ("tcp/127.0.0.1:7447",)
"""Listen endpoint used in peer mode when neither listen nor connect endpoints are configured."""

DEFAULT_SOLUTION_RATES_HZ: dict[str, float] = {"attitude": 20.0, "heading": 5.0, "azimuth": 2.0}
"""How often ``publish_solution`` publishes each NavSolution topic."""

HIGH_PRIORITY_TOPICS = frozenset({"events", "calibration"})

TLS_KEYS = {
    "root_ca": "root_ca_certificate",
    "cert": "listen_certificate",
    "key": "listen_private_key",
    "connect_cert": "connect_certificate",
    "connect_key": "connect_private_key",
}
"""``tls`` dict keys accepted by ZenohBus -> zenoh config transport/link/tls/<name>.
With cert+key we also present them when connecting (mutual TLS when enable_mtls is set)."""


def json_safe(value: Any) -> Any:
    """Non-finite floats -> None (JSON has no NaN), numpy scalars/arrays -> Python types."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return value
    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if hasattr(value, "tolist"):  # numpy array or scalar
        return json_safe(value.tolist())
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return str(value)


def _deg(rad: float | None) -> float | None:
    if rad is None or not math.isfinite(rad):
        return None
    return math.degrees(rad)


def _deg_0_360(rad: float | None) -> float | None:
    d = _deg(rad)
    if d is None:
        return None
    d %= 360.0
    return 0.0 if d >= 360.0 else d  # -1e-17 % 360 == 360.0 in floating point


def attitude_payload(sol: NavSolution) -> dict:
    """``attitude`` topic: roll/pitch (always, when levelled), yaw and q only with a valid heading."""
    valid = bool(sol.heading_valid and sol.heading_rad is not None
                 and math.isfinite(sol.heading_rad))
    q = None
    if valid and sol.q_nav_from_body is not None:
        q = [float(v) for v in sol.q_nav_from_body]
    rates = None
    if sol.rates_body_rad_s is not None:
        rates = [math.degrees(float(v)) for v in sol.rates_body_rad_s]
    return {"time_fc_s": sol.time_fc_s, "time_rx_s": sol.time_rx_s, "phase": sol.phase,
            "roll_deg": _deg(sol.roll_rad), "pitch_deg": _deg(sol.pitch_rad),
            "yaw_deg": _deg_0_360(sol.heading_rad) if valid else None,
            "roll_sigma_deg": _deg(sol.roll_sigma_rad), "pitch_sigma_deg": _deg(sol.pitch_sigma_rad),
            "heading_valid": valid, "q_nav_from_body": q, "rates_body_deg_s": rates}


def heading_payload(sol: NavSolution) -> dict:
    """``heading`` topic: the arbitrated heading, its sigma, its source and the estimator flags."""
    valid = bool(sol.heading_valid and sol.heading_rad is not None
                 and math.isfinite(sol.heading_rad))
    return {"time_fc_s": sol.time_fc_s, "time_rx_s": sol.time_rx_s, "phase": sol.phase,
            "heading_valid": valid,
            "heading_true_deg": _deg_0_360(sol.heading_rad) if valid else None,
            "heading_sigma_deg": _deg(sol.heading_sigma_rad) if valid else None,
            "heading_source": sol.heading_source, "flags": dict(sol.flags)}


def sources_payload(records: Mapping[str, AidingRecord]) -> dict:
    """Every heading source's aiding record (service/aiding.py, the Pipeline's ``aiding``) for the
    ``heading`` topic: name -> {fused, candidate, why_not, detail, time_last_fused_s,
    observation_deg, observation_sigma_deg, innovation_deg, innovation_sigma_deg, test_ratio,
    source_innovation_deg, source_innovation_sigma_deg, source_test_ratio}; degrees, null where
    unknown."""
    return {str(name): aiding_payload(rec) for name, rec in records.items()}


def air_data_payload(air: Any, time_rx_s: float, press_abs_pa: float | None = None,
                     press_diff_pa: float | None = None) -> dict:
    """``air_data`` topic from an estimators.air_data.AirData (ISA altitude, density, TAS, rate,
    pitot flags) and the raw SCALED_PRESSURE readings it came from."""
    reason = "" if air.usable else air.unusable_reason
    return {"time_fc_s": air.time_s, "time_rx_s": time_rx_s, "press_abs_pa": press_abs_pa,
            "press_diff_pa": press_diff_pa, "temperature_k": air.temperature_used_k,
            "airspeed_tas_m_s": air.tas_m_s, "air_density_kg_m3": air.density_kg_m3,
            "pressure_altitude_m": air.pressure_altitude_m,
            "alt_rate_m_s": air.alt_rate_m_s if air.rate_valid else None,
            "tas_noise_std_m_s": air.tas_noise_std_m_s,
            "usable": bool(air.usable), "unusable_reason": reason}


def calibration_payload(kind: str, status: str, detail: str, time_rx_s: float,
                        time_fc_s: float | None = None, **values: Any) -> dict:
    """``calibration`` topic: what (kind), how far (status), one line, values with units in names."""
    out = {"time_rx_s": time_rx_s, "kind": kind, "status": status, "detail": detail, **values}
    if time_fc_s is not None:
        out["time_fc_s"] = time_fc_s
    return out


def azimuth_payload(sol: NavSolution) -> dict:
    """``azimuth`` topic: the flight azimuth of method A (null until determined)."""
    return {"time_fc_s": sol.time_fc_s, "time_rx_s": sol.time_rx_s, "phase": sol.phase,
            "azimuth_true_deg": _deg_0_360(sol.azimuth_rad),
            "azimuth_sigma_deg": _deg(sol.azimuth_sigma_rad), "flags": dict(sol.flags)}


def event_payload(kind: str, severity: str, detail: str, time_rx_s: float | None = None,
                  time_fc_s: float | None = None) -> dict:
    """``events`` topic: kind (snake_case), severity (debug..critical), one line of detail."""
    out = {"time_rx_s": time.monotonic() if time_rx_s is None else time_rx_s,
           "kind": kind, "severity": severity, "detail": detail}
    if time_fc_s is not None:
        out["time_fc_s"] = time_fc_s
    return out


def health_payload(link_up: bool, phase: str, uptime_s: float, rates_hz: Mapping[str, float],
                   counters_count: Mapping[str, int] | None = None, status: str = "",
                   autopilot: str | None = None, time_rx_s: float | None = None) -> dict:
    """``health`` topic, about 1 Hz: link state, phase, received rates, counters, status line."""
    return {"time_rx_s": time.monotonic() if time_rx_s is None else time_rx_s,
            "link_up": bool(link_up), "phase": phase, "uptime_s": float(uptime_s),
            "autopilot": autopilot, "rates_hz": {k: float(v) for k, v in rates_hz.items()},
            "counters_count": {k: int(v) for k, v in (counters_count or {}).items()},
            "status": status}


def fence_geometry(cfg: Any, home_lat_deg: float, home_lon_deg: float) -> dict:
    """The fence of a service.geofence_config.GeofenceConfig as ``geofence`` fields: the launch
    site and the inclusion (the azimuth corridor included) and exclusion polygons, [lat, lon] deg."""
    from service.geofence import corridor_polygon

    incl = [[list(map(float, v)) for v in poly] for poly in cfg.inclusion]
    if cfg.corridor_azimuth_deg is not None:
        incl.append([list(v) for v in corridor_polygon(
            home_lat_deg, home_lon_deg, cfg.corridor_azimuth_deg, cfg.corridor_half_width_deg,
            cfg.corridor_range_m, cfg.corridor_home_radius_m)])
    return {"home_lat_deg": float(home_lat_deg), "home_lon_deg": float(home_lon_deg),
            "inclusion_polygons_deg": incl,
            "exclusion_polygons_deg": [[list(map(float, v)) for v in poly] for poly in cfg.exclusion]}


class ZenohBusError(RuntimeError):
    """The Zenoh session could not be opened (e.g. the listen port is taken); names the endpoints."""


@dataclass
class BusStats:
    published: dict[str, int] = field(default_factory=dict)
    errors: int = 0
    last_error: str = ""


class ZenohBus:
    """One Zenoh session, one publisher per topic, one liveliness token."""

    def __init__(self, vehicle: str, mode: str = "peer", listen: Sequence[str] | None = None,
                 connect: Sequence[str] | None = None, tls: Mapping[str, str] | None = None,
                 solution_rates_hz: Mapping[str, float] | None = None, wall_clock=time.time):
        import zenoh  # imported here: the estimators and tests that never publish skip its start-up

        if not vehicle or not all(c.isalnum() or c in "_-" for c in vehicle) or len(vehicle) > 32:
            raise ValueError(f"vehicle must be 1..32 characters [A-Za-z0-9_-], got {vehicle!r}")
        if mode not in ("peer", "client"):
            raise ValueError(f"zenoh mode must be 'peer' or 'client', got {mode!r}")
        listen = list(listen or [])
        connect = list(connect or [])
        if mode == "client" and not connect:
            raise ValueError("zenoh mode 'client' needs at least one connect endpoint (a router)")
        if mode == "peer" and not listen and not connect:
            listen = list(DEFAULT_LISTEN)
        self.vehicle = vehicle
        self.wall_clock = wall_clock
        self.listen, self.connect = listen, connect
        self.stats = BusStats(published={t: 0 for t in TOPICS})
        rates = dict(DEFAULT_SOLUTION_RATES_HZ)
        rates.update(solution_rates_hz or {})
        self._period_s = {t: (1.0 / r if r > 0 else math.inf) for t, r in rates.items()}
        self._next_s: dict[str, float] = {t: -math.inf for t in rates}

        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(connect))
        for ours, theirs in (tls or {}).items():
            if ours not in TLS_KEYS:
                raise ValueError(f"zenoh tls: unknown key {ours!r}, expected {sorted(TLS_KEYS)}")
            if value := (tls or {})[ours]:
                conf.insert_json5(f"transport/link/tls/{TLS_KEYS[ours]}", json.dumps(value))
        self._zenoh = zenoh
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise ZenohBusError(f"zenoh: cannot open a {mode} session with listen={listen} "
                                f"connect={connect}: {str(exc).split(' at /')[0]}") from None
        enc = zenoh.Encoding.APPLICATION_JSON
        self._publishers = {
            topic: self.session.declare_publisher(
                self.key(topic), encoding=enc,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=(zenoh.Priority.DATA_HIGH if topic in HIGH_PRIORITY_TOPICS
                          else zenoh.Priority.DATA))
            for topic in TOPICS}
        self.token = self.session.liveliness().declare_token(self.key("alive"))
        self.closed = False
        log.info("zenoh bus open", extra={"fields": {"vehicle": vehicle, "mode": mode,
                                                      "listen": listen, "connect": connect}})

    def key(self, topic: str) -> str:
        return f"{KEY_PREFIX}/{self.vehicle}/{topic}"

    def publish(self, topic: str, payload: Mapping[str, Any]) -> bool:
        """Publish one payload (``schema``, ``vehicle`` and ``time_unix_s`` set here: the bus owns
        the wire format, a payload's own ``schema`` is replaced). True when handed to Zenoh.
        Unknown topic or a non-dict payload: ValueError (a programming error)."""
        if topic not in self._publishers:
            raise ValueError(f"unknown topic {topic!r}, expected one of {list(TOPICS)}")
        if not isinstance(payload, Mapping):
            raise ValueError(f"payload for {topic} must be a dict, got {type(payload).__name__}")
        if self.closed:
            return False
        body = json_safe(payload)
        body.update(schema=SCHEMA_VERSION, vehicle=self.vehicle, time_unix_s=self.wall_clock())
        try:
            self._publishers[topic].put(json.dumps(body, separators=(",", ":")))
        except self._zenoh.ZError as exc:  # the daemon must not die because a put failed
            self.stats.errors += 1
            self.stats.last_error = str(exc)
            return False
        self.stats.published[topic] += 1
        return True

    def _due(self, topic: str, now_s: float) -> bool:
        if now_s < self._next_s[topic]:
            return False
        nxt = self._next_s[topic] + self._period_s[topic]
        self._next_s[topic] = nxt if nxt > now_s else now_s + self._period_s[topic]
        return True

    def publish_solution(self, sol: NavSolution, now_s: float,
                         aiding: Mapping[str, AidingRecord] | None = None) -> list[str]:
        """Publish attitude / heading / azimuth from one NavSolution when each is due at local
        monotonic time ``now_s`` (rates ``DEFAULT_SOLUTION_RATES_HZ``); ``aiding`` (the aiding
        record of every heading source, Pipeline.aiding) goes into ``heading`` as ``sources``.
        Returns the topics sent."""
        sent = []
        for topic, build in (("attitude", attitude_payload), ("heading", heading_payload),
                             ("azimuth", azimuth_payload)):
            if not self._due(topic, now_s):
                continue
            payload = build(sol)
            if topic == "heading" and aiding:
                payload["sources"] = sources_payload(aiding)
            if self.publish(topic, payload):
                sent.append(topic)
        return sent

    def close(self) -> None:
        """Withdraw the liveliness token and close the session (idempotent)."""
        if self.closed:
            return
        self.closed = True
        try:
            self.token.undeclare()
            for pub in self._publishers.values():
                pub.undeclare()
            self.session.close()
        except self._zenoh.ZError as exc:
            log.warning("zenoh close failed", extra={"fields": {"error": str(exc)}})

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
