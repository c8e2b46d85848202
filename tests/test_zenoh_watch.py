"""``azimuthd watch`` in its own process sees what a ZenohBus publishes, for two vehicles."""
from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from estimators.rotations import quat_from_euler
from mavlink_io.navsolution import NavSolution
from service.watch import GONE_AFTER_S, WatchState, main, open_session, render, subscribe
from service.zenoh_bus import ZenohBus, event_payload, health_payload


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sol(heading_deg: float) -> NavSolution:
    yaw = math.radians(heading_deg)
    return NavSolution(time_fc_s=10.0, time_rx_s=time.monotonic(), phase="in-flight",
                       q_nav_from_body=quat_from_euler(0.05, -0.1, yaw), roll_rad=0.05,
                       pitch_rad=-0.1, rates_body_rad_s=np.zeros(3),
                       heading_rad=yaw, heading_sigma_rad=math.radians(1.5),
                       heading_source="azimuth", heading_valid=True,
                       azimuth_rad=math.radians(heading_deg - 2.0),
                       azimuth_sigma_rad=math.radians(1.0))


def publish_until(stop: threading.Event, buses: dict[str, tuple[ZenohBus, float]]) -> None:
    while not stop.is_set():
        for name, (bus, hdg) in buses.items():
            bus.publish_solution(sol(hdg), time.monotonic())
            bus.publish("health", health_payload(True, "in-flight", 5.0, {"RAW_IMU": 200.0}))
        time.sleep(0.05)


def run_watch(args: list[str]) -> subprocess.CompletedProcess:
    code = "import sys; from service.watch import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          timeout=40)


def test_watch_process_shows_two_vehicles():
    ep1, ep2 = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    buses = {"uav3": (ZenohBus("uav3", "peer", [ep1], []), 231.2),
             "uav4": (ZenohBus("uav4", "peer", [ep2], []), 12.5)}
    stop = threading.Event()
    th = threading.Thread(target=publish_until, args=(stop, buses), daemon=True)
    th.start()
    buses["uav3"][0].publish("events", event_payload("launch_detected", "notice", "boost"))
    try:
        proc = run_watch(["--connect", ep1, "--connect", ep2, "--duration", "3", "--json"])
        table = run_watch(["--connect", ep1, "--once", "--vehicle", "uav3", "--duration", "10"])
    finally:
        stop.set()
        th.join(timeout=5)
        for bus, _ in buses.values():
            bus.close()
    assert proc.returncode == 0, proc.stderr
    snap = json.loads(proc.stdout)
    assert set(snap["vehicles"]) == {"uav3", "uav4"}
    for name, hdg in (("uav3", 231.2), ("uav4", 12.5)):
        v = snap["vehicles"][name]
        assert v["alive"] is True
        assert v["schema_errors"] == 0, v["last_schema_error"]
        assert v["latest"]["heading"]["heading_true_deg"] == pytest.approx(hdg, abs=1e-9)
        assert v["latest"]["attitude"]["pitch_deg"] == pytest.approx(math.degrees(-0.1), abs=1e-9)
        assert v["counts"]["attitude"] >= 10  # 20 Hz for ~3 s, allowing for connection set-up
    assert table.returncode == 0, table.stderr
    assert "uav3" in table.stdout and "uav4" not in table.stdout
    assert "231.2 ±1.5" in table.stdout and "229.2 ±1.0" in table.stdout


def test_watch_state_flags_schema_errors_and_liveliness():
    st = WatchState()
    st.on_liveliness("azimuthd/uav1/alive", True)
    st.on_sample("azimuthd/uav1/heading", json.dumps({"schema": "azimuthd/1", "vehicle": "uav1"}))
    st.on_sample("azimuthd/uav1/gps", "{}")
    st.on_sample("other/uav1/heading", "{}")  # not ours: ignored
    snap = st.snapshot()["vehicles"]["uav1"]
    assert snap["alive"] is True and snap["schema_errors"] == 2
    st.on_liveliness("azimuthd/uav1/alive", False)
    assert st.snapshot()["vehicles"]["uav1"]["alive"] is False
    assert not st.complete()


def test_watch_exits_1_and_says_so_when_no_daemon_is_found(capsys):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    assert main(["--connect", endpoint, "--duration", "0.5", "--json"]) == 1
    err = capsys.readouterr().err
    assert f"no azimuthd found on {endpoint}" in err and "[zenoh] listen" in err
    assert "Traceback" not in err


def test_watch_refuses_a_malformed_endpoint_in_one_line(capsys):
    assert main(["--connect", "127.0.0.1:7447", "--duration", "0.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("azimuthd watch: cannot open a Zenoh peer session to 127.0.0.1:7447")
    assert "\n" not in err and "Traceback" not in err


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def test_a_silent_vehicle_is_gone_after_the_timeout():
    """GIVEN a vehicle whose token is present WHEN nothing arrives for GONE_AFTER_S THEN GONE
    (a hung daemon keeps its token: the Zenoh session threads outlive the loop)."""
    clock = FakeClock()
    st = WatchState(clock=clock)
    st.on_liveliness("azimuthd/uav1/alive", True)
    assert st.snapshot()["vehicles"]["uav1"]["status"] == "starting"
    st.on_sample("azimuthd/uav1/health", json.dumps(
        {"schema": "azimuthd/1", "vehicle": "uav1", **health_payload(True, "boot", 1.0, {})}))
    clock.now_s += GONE_AFTER_S - 0.1
    assert st.snapshot()["vehicles"]["uav1"]["status"] == "alive"
    clock.now_s += 0.2
    v = st.snapshot()["vehicles"]["uav1"]
    assert (v["status"], v["status_reason"]) == ("GONE", f"nothing received for {GONE_AFTER_S:.0f} s")
    st.on_sample("azimuthd/uav1/health", json.dumps(
        {"schema": "azimuthd/1", "vehicle": "uav1", **health_payload(True, "boot", 7.0, {})}))
    assert st.snapshot()["vehicles"]["uav1"]["status"] == "alive"  # heard again: back


def wait_until(cond, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def test_a_daemon_that_closes_is_shown_gone_not_link_up():
    """GIVEN watch's subscriptions on a live bus reporting link up WHEN the bus closes (the
    daemon stops) THEN the vehicle is GONE because its token was withdrawn, and the table shows
    GONE and no longer 'up'."""
    from rich.console import Console

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = ZenohBus("uav5", "peer", [endpoint], [])
    state = WatchState()
    session = open_session([endpoint], "peer")
    subs = subscribe(session, state)
    try:
        def heard() -> bool:
            bus.publish("health", health_payload(True, "in-flight", 5.0, {"RAW_IMU": 200.0}))
            v = state.snapshot()["vehicles"].get("uav5")
            return v is not None and v["status"] == "alive" and "health" in v["latest"]
        assert wait_until(heard, 15.0), state.snapshot()
        bus.close()
        assert wait_until(lambda: state.snapshot()["vehicles"]["uav5"]["alive"] is False, 15.0)
        v = state.snapshot()["vehicles"]["uav5"]
        assert v["status"] == "GONE" and "token withdrawn" in v["status_reason"]
        console = Console(width=200, record=True)
        console.print(render(state, [endpoint]))
        row = next(line for line in console.export_text().splitlines() if "uav5" in line)
        assert "GONE" in row and " up " not in row
    finally:
        bus.close()
        for sub in subs:
            sub.undeclare()
        session.close()
