"""Zenoh bus: a subscriber in another process receives every topic, payloads valid against the
one schema file, and sees the liveliness token appear and disappear."""
from __future__ import annotations

import json
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time

import jsonschema
import numpy as np
import pytest

from estimators.rotations import quat_from_euler
from service import schema
from mavlink_io.navsolution import NavSolution
from service.zenoh_bus import (ZenohBus, air_data_payload, attitude_payload, azimuth_payload,
                               calibration_payload, event_payload, fence_geometry, heading_payload,
                               health_payload, json_safe, sources_payload, ZenohBusError)

WALL_S = 1_800_000_000.25
"""The wall clock the test buses publish with (``time_unix_s``)."""

SUBSCRIBER = r"""
import json, sys, time, zenoh
endpoint, deadline_s = sys.argv[1], float(sys.argv[2])
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
session = zenoh.open(conf)
done = []
def out(obj):
    sys.stdout.write(json.dumps(obj) + "\n"); sys.stdout.flush()
def on_data(s):
    out({"kind": "data", "key": str(s.key_expr), "encoding": str(s.encoding),
         "payload": json.loads(s.payload.to_string())})
def on_live(s):
    op = "PUT" if s.kind == zenoh.SampleKind.PUT else "DELETE"
    out({"kind": "live", "key": str(s.key_expr), "op": op})
    if op == "DELETE":
        done.append(1)
sub = session.declare_subscriber("azimuthd/*/**", on_data)
live = session.liveliness().declare_subscriber("azimuthd/*/alive", on_live, history=True)
out({"kind": "ready"})
t_end = time.monotonic() + deadline_s
while not done and time.monotonic() < t_end:
    time.sleep(0.02)
session.close()
"""

HOLDER = r"""
import sys, time
from service.zenoh_bus import ZenohBus
bus = ZenohBus("uav9", "peer", [sys.argv[1]], [])
print("open", flush=True)
time.sleep(60)
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def validator():
    return jsonschema.Draft202012Validator(schema.load_schema())


def check_with_jsonschema(topic: str, payload: dict) -> None:
    sub = {"$ref": f"#/$defs/{topic}", "$defs": schema.load_schema()["$defs"]}
    jsonschema.Draft202012Validator(sub).validate(payload)


def solution(**kw) -> NavSolution:
    roll, pitch, yaw = math.radians(3.0), math.radians(-12.0), math.radians(359.9999999)
    base = dict(time_fc_s=42.5, time_rx_s=1234.25, phase="in-flight",
                q_nav_from_body=quat_from_euler(roll, pitch, yaw), roll_rad=roll, pitch_rad=pitch,
                rates_body_rad_s=np.array([0.01, 0.02, -0.03]), roll_sigma_rad=0.004,
                pitch_sigma_rad=0.005, heading_rad=yaw, heading_sigma_rad=math.radians(2.5),
                heading_source="azimuth", heading_valid=True, azimuth_rad=math.radians(47.0),
                azimuth_sigma_rad=math.radians(1.2), flags={"azimuth_gate": "ok"})
    base.update(kw)
    return NavSolution(**base)


def all_topic_payloads() -> dict[str, dict]:
    sol = solution()
    return {
        "attitude": attitude_payload(sol),
        "heading": heading_payload(sol),
        "azimuth": azimuth_payload(sol),
        "air_data": {"time_fc_s": 42.5, "press_abs_pa": 98000.0, "press_diff_pa": 310.0,
                     "temperature_k": 290.0, "airspeed_ias_m_s": 22.5,
                     "airspeed_tas_m_s": float("nan")},
        "calibration": {"time_rx_s": 1234.0, "kind": "gyro_bias", "status": "done",
                        "gyro_bias_rad_s": [1e-4, -2e-4, 3e-5], "still_s": 2.0},
        "geofence": {"time_fc_s": 42.5, "state": "inside", "distance_to_boundary_m": 812.0,
                     "bearing_to_boundary_deg": 90.0, "action": "RTL", "action_result": None},
        "health": health_payload(True, "in-flight", 61.0, {"RAW_IMU": 200.0},
                                 {"crc_errors": 0, "imu_rejected": 2}, "ok", "ardupilot",
                                 time_rx_s=1234.0),
        "events": event_payload("launch_detected", "notice", "|f| 31.2 m/s2 for 0.05 s",
                                time_rx_s=1234.0, time_fc_s=40.1),
    }


class Lines:
    """Reads a child's stdout lines in a thread so the test can wait with a timeout."""

    def __init__(self, proc: subprocess.Popen):
        self.q: queue.Queue = queue.Queue()
        threading.Thread(target=self._pump, args=(proc.stdout,), daemon=True).start()

    def _pump(self, stream) -> None:
        for line in stream:
            self.q.put(line)

    def wait_for(self, pred, timeout_s: float, sink: list | None = None):
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            try:
                obj = json.loads(self.q.get(timeout=0.05))
            except queue.Empty:
                continue
            if sink is not None:
                sink.append(obj)
            if pred(obj):
                return obj
        return None


def test_subscriber_process_receives_every_topic_and_liveliness():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint, "20"],
                           stdout=subprocess.PIPE, text=True)
    try:
        lines = Lines(sub)
        assert lines.wait_for(lambda o: o["kind"] == "ready", 15.0), "subscriber did not start"
        bus = ZenohBus("uav7", "peer", [endpoint], [], wall_clock=lambda: WALL_S)
        try:
            alive = lines.wait_for(lambda o: o["kind"] == "live", 10.0)
            assert alive == {"kind": "live", "key": "azimuthd/uav7/alive", "op": "PUT"}
            payloads = all_topic_payloads()
            received: dict[str, dict] = {}
            t_end = time.monotonic() + 10.0
            while len(received) < len(payloads) and time.monotonic() < t_end:
                for topic, payload in payloads.items():
                    if topic not in received:
                        assert bus.publish(topic, payload)
                got: list = []
                lines.wait_for(lambda o: False, 0.1, got)
                for obj in got:
                    if obj["kind"] == "data":
                        received[obj["key"].rsplit("/", 1)[1]] = obj
            assert set(received) == set(schema.TOPICS)
        finally:
            bus.close()
        gone = lines.wait_for(lambda o: o["kind"] == "live", 10.0)
        assert gone == {"kind": "live", "key": "azimuthd/uav7/alive", "op": "DELETE"}
    finally:
        sub.wait(timeout=20)
    for topic, obj in received.items():
        assert obj["key"] == f"azimuthd/uav7/{topic}"
        assert obj["encoding"].startswith("application/json")
        payload = obj["payload"]
        assert payload["schema"] == "azimuthd/1" and payload["vehicle"] == "uav7"
        assert payload["time_unix_s"] == WALL_S  # every topic carries the wall clock
        assert schema.validate(topic, payload) == [], (topic, payload)
        check_with_jsonschema(topic, payload)
    att = received["attitude"]["payload"]
    assert att["roll_deg"] == pytest.approx(3.0, abs=1e-9)
    assert 0.0 <= att["yaw_deg"] < 360.0  # 359.9999999 deg stays below 360
    assert received["air_data"]["payload"]["airspeed_tas_m_s"] is None  # NaN -> null
    assert received["heading"]["payload"]["heading_sigma_deg"] == pytest.approx(2.5)
    assert received["azimuth"]["payload"]["azimuth_true_deg"] == pytest.approx(47.0)


def test_liveliness_disappears_when_the_holding_process_dies():
    import zenoh

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, endpoint], stdout=subprocess.PIPE,
                              text=True, cwd=os.path.dirname(os.path.dirname(__file__)))
    events: queue.Queue = queue.Queue()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    session = zenoh.open(conf)
    try:
        assert holder.stdout.readline().strip() == "open"
        session.liveliness().declare_subscriber(
            "azimuthd/*/alive", lambda s: events.put((str(s.key_expr), s.kind)), history=True)
        assert events.get(timeout=10) == ("azimuthd/uav9/alive", zenoh.SampleKind.PUT)
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
        assert events.get(timeout=15) == ("azimuthd/uav9/alive", zenoh.SampleKind.DELETE)
    finally:
        if holder.poll() is None:
            holder.kill()
        session.close()


def test_publish_validation_and_defaults():
    with pytest.raises(ValueError, match="vehicle"):
        ZenohBus("bad/name")
    with pytest.raises(ValueError, match="client"):
        ZenohBus("uav1", "client", [], [])
    with pytest.raises(ValueError, match="tls: unknown key"):
        ZenohBus("uav1", "peer", [f"tcp/127.0.0.1:{free_port()}"], [], {"pem": "x"})
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = ZenohBus("uav1", "peer", [endpoint], [])
    try:
        with pytest.raises(ZenohBusError, match="listen=.*Address already in use"):
            ZenohBus("uav2", "peer", [endpoint], [])  # a second daemon on the same port
        with pytest.raises(ValueError, match="unknown topic"):
            bus.publish("gps", {})
        with pytest.raises(ValueError, match="must be a dict"):
            bus.publish("events", [1])
        # publish_solution: per-topic rates (attitude 20 Hz, heading 5 Hz, azimuth 2 Hz)
        sent: dict[str, int] = {}
        for k in range(200):  # 1 s of 200 Hz solutions
            for t in bus.publish_solution(solution(), 100.0 + k * 0.005):
                sent[t] = sent.get(t, 0) + 1
        assert sent == {"attitude": 20, "heading": 5, "azimuth": 2}
    finally:
        bus.close()
    assert bus.publish("events", event_payload("x", "info", "after close")) is False
    bus.close()  # idempotent


def test_payload_helpers_without_heading():
    sol = solution(heading_valid=False, azimuth_rad=None, azimuth_sigma_rad=None)
    for topic, payload in (("attitude", attitude_payload(sol)), ("heading", heading_payload(sol)),
                           ("azimuth", azimuth_payload(sol))):
        full = json_safe({"schema": "azimuthd/1", "vehicle": "uav1", **payload})
        assert schema.validate(topic, full) == []
        check_with_jsonschema(topic, full)
    assert attitude_payload(sol)["yaw_deg"] is None
    assert attitude_payload(sol)["q_nav_from_body"] is None
    assert heading_payload(sol)["heading_true_deg"] is None
    assert azimuth_payload(sol)["azimuth_true_deg"] is None


BAD = [
    ("attitude", {"roll_deg": 200.0}),                    # out of range
    ("attitude", {"yaw_deg": 360.0}),                     # [0, 360)
    ("heading", {"heading_source": "gps"}),               # not a source name
    ("heading", {"heading_source": "azimuth+"}),          # a dangling '+'
    ("heading", {"sources": {"fc": {"fused": "yes", "candidate": True, "why_not": "", "detail": "",
                                    "time_last_fused_s": 1.0, "observation_deg": 1.0, "observation_sigma_deg": 1.0,
                                    "innovation_deg": 0.0, "innovation_sigma_deg": 1.0, "test_ratio": 0.0}}}),  # fused: a boolean
    ("heading", {"sources": {"fc": {"fused": False, "candidate": True, "why_not": "it felt wrong", "detail": "",
                                    "time_last_fused_s": None, "observation_deg": 1.0, "observation_sigma_deg": 1.0,
                                    "innovation_deg": 0.0, "innovation_sigma_deg": 1.0, "test_ratio": 0.0}}}),  # not a code
    ("air_data", {"usable": 1.0}),                        # a flag, not a number
    ("heading", {"heading_valid": "yes"}),                # wrong type
    ("attitude", {"q_nav_from_body": [1.0, 0.0, 0.0]}),   # 3 items
    ("air_data", {"airspeed": 3.0}),                      # extra field without a unit
    ("calibration", {"status": "ok"}),                    # not in the enum
    ("events", {"kind": "Launch Detected"}),              # not snake_case
    ("health", {"rates_hz": {"RAW_IMU": -1.0}}),          # negative rate
    ("geofence", {"colour": "red"}),                      # unknown field
    ("azimuth", {"schema": "azimuthd/0"}),                # wrong version
]


@pytest.mark.parametrize("topic,change", BAD)
def test_schema_rejects_bad_payloads_like_jsonschema(topic, change):
    good = json_safe({"schema": "azimuthd/1", "vehicle": "uav1", **all_topic_payloads()[topic]})
    assert schema.validate(topic, good) == []
    check_with_jsonschema(topic, good)
    bad = {**good, **change}
    assert schema.validate(topic, bad) != []
    with pytest.raises(jsonschema.ValidationError):
        check_with_jsonschema(topic, bad)
    missing = {k: v for k, v in good.items() if k != "schema"}
    assert any("missing required field 'schema'" in e for e in schema.validate(topic, missing))


def test_schema_file_is_valid_json_schema():
    jsonschema.Draft202012Validator.check_schema(schema.load_schema())
    assert set(schema.load_schema()["$defs"]) >= set(schema.TOPICS)
    with pytest.raises(ValueError, match="unknown topic"):
        schema.validate("gps", {})


def test_published_forms_of_the_heading_source_are_valid():
    """GIVEN the arbitration's source strings (fused sources joined by '+', 'coast', 'none')
    WHEN they are published in a heading payload THEN the schema (and jsonschema) accept them."""
    for source in ("azimuth", "azimuth+fc", "heading_filter+synthetic_ahrs", "coast", "none"):
        payload = json_safe({"schema": "azimuthd/1", "vehicle": "uav1",
                             **heading_payload(solution(heading_source=source))})
        assert schema.validate("heading", payload) == [], source
        check_with_jsonschema("heading", payload)


def test_sources_air_data_calibration_and_fence_payloads_match_the_schema():
    """GIVEN the daemon's real producers (an arbitration verdict, an AirData, a GeofenceMonitor)
    WHEN they are turned into payloads as the daemon does THEN each validates against the schema."""
    import dataclasses

    from estimators.air_data import AirData
    from service.geofence import GeofenceMonitor
    from service.geofence_config import validate_geofence

    from service.aiding import NotOffered
    from service.heading_arbitration import ArbitrationState, SourceReading, arbitrate
    from service.heading_sources import deviation_record

    # the arbitration's records: A fused, the FC gated out, C inconsistent, B not offered, and D
    st, _ = arbitrate(ArbitrationState(), [SourceReading("azimuth", math.radians(100.0), math.radians(0.5), True, 9.9)], 9.9)
    _, out = arbitrate(st, [SourceReading("azimuth", math.radians(100.0), math.radians(0.5), True, 10.0),
                            SourceReading("fc", math.radians(120.0), math.radians(2.0), True, 10.0),
                            SourceReading("heading_filter", math.radians(101.0), math.radians(3.0), True, 10.0,
                                          consistent=False, why_not="its magnetometer innovations gated out for 2.1 s",
                                          source_innovation_rad=math.radians(25.0),
                                          source_innovation_variance_rad2=math.radians(4.0) ** 2,
                                          source_test_ratio=4.3)],
                       10.0, not_offered=(NotOffered("synthetic_ahrs", "superseded", "method A has a solution"),))
    records = dict(out.records, deviation=deviation_record(10.0, None, True, None, None, 0.8, math.nan))
    heading = heading_payload(solution())
    heading["sources"] = sources_payload(records)
    fc = heading["sources"]["fc"]
    assert (fc["fused"], fc["candidate"], fc["why_not"]) == (False, True, "gated_out")
    assert fc["innovation_deg"] == pytest.approx(20.0) and fc["test_ratio"] > 1.0
    assert heading["sources"]["azimuth"]["time_last_fused_s"] == 10.0
    c = heading["sources"]["heading_filter"]
    assert (c["why_not"], c["source_innovation_deg"], c["source_test_ratio"]) == ("inconsistent", pytest.approx(25.0), 4.3)
    assert heading["sources"]["synthetic_ahrs"]["innovation_deg"] is None
    air = AirData(time_s=42.5, pressure_altitude_m=412.0, density_kg_m3=1.18, temperature_used_k=285.0,
                  tas_m_s=23.5, alt_rate_m_s=1.5, tas_noise_std_m_s=0.2, airspeed_low=False,
                  pitot_blocked=False, pitot_noisy=False, rate_valid=True)
    blocked = dataclasses.replace(air, pitot_blocked=True, rate_valid=False)
    cfg = validate_geofence({"enabled": True, "inclusion": [[[47.27, 8.46], [47.27, 8.53], [47.32, 8.53]]],
                             "corridor_azimuth_deg": 40.0, "actions": ["rtl"]})
    mon = GeofenceMonitor(cfg, 47.29, 8.49, 400.0)
    fence = {**mon.state(), **fence_geometry(cfg, 47.29, 8.49)}
    payloads = [("heading", heading), ("air_data", air_data_payload(air, 1234.0, 96000.0, 330.0)),
                ("air_data", air_data_payload(blocked, 1234.5, 96000.0, 330.0)),
                ("calibration", calibration_payload("levelling", "done", "roll 1.0 pitch 2.0", 12.0, 3.0,
                                                    roll_deg=1.0, gyro_bias_rad_s=[1e-4, 0.0, -1e-4])),
                ("geofence", fence)]
    for topic, payload in payloads:
        body = json_safe(payload)
        body.update(schema="azimuthd/1", vehicle="uav1", time_unix_s=WALL_S)  # as ZenohBus.publish
        assert schema.validate(topic, body) == [], (topic, schema.validate(topic, body))
        check_with_jsonschema(topic, body)
    assert air_data_payload(blocked, 0.0)["unusable_reason"] == "pitot blocked"
    assert air_data_payload(blocked, 0.0)["alt_rate_m_s"] is None  # not settled: unknown, not 0
    assert len(fence["inclusion_polygons_deg"]) == 2  # the configured polygon and the corridor
    assert fence["inclusion_polygons_deg"][0][1] == [47.27, 8.53]
