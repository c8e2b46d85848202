"""``azimuthd web`` in a real browser (headless Chromium driven by selenium), against the bundled
simulator and the daemon, as a user runs them: three processes on loopback (sim -> MAVLink ->
daemon -> Zenoh -> web -> SSE -> Chromium).

GIVEN `azimuthd sim` (inclined rail, at rest before launch), `azimuthd run` publishing on Zenoh
      with a geofence, and `azimuthd web` connected to it
WHEN the page is loaded in Chromium
THEN it shows the vehicle by name (and a second vehicle of the test's own in its own card), the phase, a heading equal (to its 0.1 deg display) to the
     `heading` payload the daemon published for the same FC time, the heading sources the daemon
     reported with which one is used, link up, the fence; every topic the daemon published
     validates against the schema and carries `time_unix_s`; and when the daemon stops the page
     shows it GONE.

Chromium and chromedriver are Debian's packages (`apt-get install chromium chromium-driver`; .ci/run
installs them). Outside CI the browser tests are skipped, with the reason, when they are absent (the
topic checks still run).
AZIMUTHD_DASHBOARD_PNG=PATH also saves the screenshot there; docs/dashboard.png is made with
AZIMUTHD_DASHBOARD_WAIT_S=150 (a longer flight, GNSS lost 15 s after the launch: the track is dead
reckoned) and AZIMUTHD_DASHBOARD_PNG=docs/dashboard.png.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from service import schema
from service.web.hub import Client, Hub

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import Sitl, scenario_site  # noqa: E402
from conftest import HANG_S, cpu_seconds, wait_progressing  # noqa: E402

VEHICLE = "uav-web"
OTHER = "uav-x2"
"""A second vehicle on the same page: a ZenohBus of the test's own, heading OTHER_HEADING_DEG."""
OTHER_HEADING_DEG = 123.4
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
HEADING_DISPLAY_TOL_DEG = 0.05 + 1e-9
"""The page shows the heading with one decimal: rounding is the only difference allowed."""


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_live(live, cond, what):
    """Until ``cond()``, for as long as the simulator, the daemon and the web server work (their
    CPU time): a busy machine delays what the page and the daemon show, never fails the wait."""
    s = live["sitl"]
    return wait_progressing(cond, lambda: cpu_seconds(*(p for p in (s.sim, s.daemon, live["web"]) if p)), what)


# --- the hub and the command line, without a browser ---------------------------------------------

def test_hub_fans_out_keeps_the_track_and_drops_the_oldest_for_a_slow_browser():
    """GIVEN a browser connected to the hub WHEN more messages arrive than its queue holds THEN
    it loses the oldest (counted), keeps the newest; geofence positions make the track; events
    and calibrations are kept for a browser that connects later."""
    hub = Hub(["tcp/127.0.0.1:1"])
    client = hub.connect()
    first = json.loads(client.queue.get_nowait())
    assert first["type"] == "snapshot" and first["status"]["no_daemon"] is True
    assert "no azimuthd found on tcp/127.0.0.1:1" in first["status"]["message"]
    small = Client(maxsize=3)
    hub.clients.append(small)
    for k in range(5):
        body = json.dumps({"schema": "azimuthd/1", "vehicle": "uav1", "time_fc_s": float(k),
                           "state": "ok", "lat_deg": 47.0 + k * 1e-4, "lon_deg": 8.0})
        hub.state.on_sample("azimuthd/uav1/geofence", body)
        hub.on_sample("azimuthd/uav1/geofence", body)
    assert small.dropped == 2
    kept = [json.loads(small.queue.get_nowait())["payload"]["time_fc_s"] for _ in range(3)]
    assert kept == [2.0, 3.0, 4.0]
    assert hub.snapshot()["tracks"]["uav1"] == [[47.0 + k * 1e-4, 8.0] for k in range(5)]
    # a browser connecting later gets every vehicle's recent events and each calibration kind's last
    for k, (kind, status) in enumerate((("levelling", "done"), ("mag_error_kf1", "started"),
                                        ("mag_error_kf1", "saved"))):
        hub.on_sample("azimuthd/uav1/calibration", json.dumps(
            {"schema": "azimuthd/1", "vehicle": "uav1", "time_rx_s": float(k), "kind": kind,
             "status": status, "detail": ""}))
    for k in range(45):
        hub.on_sample(f"azimuthd/uav{1 + k % 2}/events", json.dumps(
            {"schema": "azimuthd/1", "time_rx_s": float(k), "time_unix_s": 1.8e9 + k, "kind": f"e{k}",
             "severity": "info", "detail": ""}))
    snap = hub.snapshot()
    assert {(c["kind"], c["status"]) for c in snap["calibrations"]["uav1"]} == {("levelling", "done"),
                                                                                ("mag_error_kf1", "saved")}
    assert [e["kind"] for e in snap["events"]] == [f"e{k}" for k in range(45)]  # 23 + 22 < 40 each
    assert {e["vehicle"] for e in snap["events"]} == {"uav1", "uav2"}
    hub.on_liveliness("azimuthd/uav1/alive", False)
    hub.state.on_liveliness("azimuthd/uav1/alive", False)
    assert hub.status()["vehicles"]["uav1"]["status"] == "GONE"
    hub.disconnect(client)
    assert client not in hub.clients


def run_web(args: list[str], timeout_s: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", "web", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout_s)


def test_web_refuses_a_busy_port_a_bad_endpoint_and_an_unreachable_router_in_one_line():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        taken = run_web(["--listen", f"127.0.0.1:{port}", "--duration", "1"])
    assert taken.returncode == 2
    assert taken.stderr.strip() == (f"azimuthd web: cannot listen on 127.0.0.1:{port}: address already in "
                                    "use (another azimuthd web? choose another --listen HOST:PORT)")
    bad = run_web(["--connect", "localhost:7447", "--listen", f"127.0.0.1:{free_tcp_port()}",
                   "--duration", "1"])
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.startswith("azimuthd web: cannot open a Zenoh peer session to localhost:7447")
    assert len(bad.stderr.strip().splitlines()) == 1
    router = f"tcp/127.0.0.1:{free_tcp_port()}"  # nobody there: a client session cannot open
    gone = run_web(["--mode", "client", "--connect", router, "--listen", f"127.0.0.1:{free_tcp_port()}",
                    "--duration", "1"])
    assert gone.returncode == 2 and gone.stderr.strip() == (
        f"azimuthd web: cannot open a Zenoh client session to {router}: Unable to connect to any of "
        f"[Single({router})]!")
    form = run_web(["--listen", "8765"])
    assert form.returncode == 2 and "--listen must be HOST:PORT" in form.stderr


# --- the browser ---------------------------------------------------------------------------------

def _browser_or_skip():
    if CHROMIUM and CHROMEDRIVER:
        return
    why = ("chromium and chromedriver not installed (Debian: apt-get install chromium chromium-driver; "
           ".ci/run installs them)")
    if os.environ.get("CI"):
        pytest.fail(why)
    pytest.skip(why)


def chrome(user_data_dir: Path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--window-size=1500,1100", f"--user-data-dir={user_data_dir}"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    # explicit binaries: selenium's driver manager never goes to the network
    return webdriver.Chrome(options=opts, service=Service(executable_path=CHROMEDRIVER))


class ZenohRecorder:
    """The test's own subscriber: what the daemon published, to compare the page with."""

    def __init__(self, endpoint: str):
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.session = zenoh.open(conf)
        self.lock = threading.Lock()
        self.by_topic: dict[str, list[dict]] = {}
        self.sub = self.session.declare_subscriber(f"azimuthd/{VEHICLE}/**", self._on)

    def _on(self, s) -> None:
        topic = str(s.key_expr).rsplit("/", 1)[1]
        with self.lock:
            self.by_topic.setdefault(topic, []).append(json.loads(s.payload.to_string()))

    def get(self, topic: str) -> list[dict]:
        with self.lock:
            return list(self.by_topic.get(topic, []))

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def publish_other(stop: threading.Event, endpoint: str) -> None:
    """The second vehicle: a fixed attitude and heading, its health, until ``stop``."""
    import math

    import numpy as np

    from estimators.rotations import quat_from_euler
    from mavlink_io.navsolution import NavSolution
    from service.zenoh_bus import ZenohBus, health_payload

    yaw = math.radians(OTHER_HEADING_DEG)
    with ZenohBus(OTHER, "peer", [endpoint], []) as bus:
        k = 0
        while not stop.is_set():
            sol = NavSolution(time_fc_s=10.0 + 0.1 * k, time_rx_s=time.monotonic(), phase="in-flight",
                              q_nav_from_body=quat_from_euler(0.1, 0.05, yaw), roll_rad=0.1, pitch_rad=0.05,
                              rates_body_rad_s=np.zeros(3), heading_rad=yaw, heading_sigma_rad=math.radians(2.0),
                              heading_source="heading_filter", heading_valid=True)
            bus.publish_solution(sol, time.monotonic())
            if k % 10 == 0:
                bus.publish("health", health_payload(True, "in-flight", 0.1 * k, {"RAW_IMU": 50.0}))
            k += 1
            stop.wait(0.1)


def fence_around(site: dict, half_deg: float = 0.02) -> list:
    la, lo = site["lat_deg"], site["lon_deg"]
    return [[[la - half_deg, lo - half_deg], [la - half_deg, lo + half_deg],
             [la + half_deg, lo + half_deg], [la + half_deg, lo - half_deg]]]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """sim + daemon + web (+ Chromium when installed: the topic checks run without it)."""
    wd = tmp_path_factory.mktemp("web")
    zenoh_ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    other_ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    http_port = free_tcp_port()
    site = scenario_site("inclined_rail")["site"]
    overrides = {"vehicle": {"name": VEHICLE}, "zenoh": {"enabled": True, "listen": [zenoh_ep]},
                 "geofence": {"enabled": True, "inclusion": fence_around(site), "actions": ["rtl"]}}
    sim_args = ["--duration", "400"]
    if float(os.environ.get("AZIMUTHD_DASHBOARD_WAIT_S", "0")) > 0:
        sim_args += ["--set", "gnss.lost_at_s=75"]  # the documentation's flight: dead reckoning after 15 s
    sitl = Sitl(scenario="inclined_rail", speed=1.0, seed=5, workdir=wd, config_overrides=overrides,
                sim_args=sim_args)
    web = subprocess.Popen([sys.executable, "-m", "service.cli", "web", "--connect", zenoh_ep,
                            "--connect", other_ep, "--listen", f"127.0.0.1:{http_port}"], cwd=ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
    recorder = driver = None
    stop_other = threading.Event()
    other = threading.Thread(target=publish_other, args=(stop_other, other_ep), daemon=True)
    try:
        other.start()
        recorder = ZenohRecorder(zenoh_ep)
        line = web.stdout.readline()
        assert "azimuthd web: serving http://127.0.0.1:" in line, line
        sitl.__enter__()
        if CHROMIUM and CHROMEDRIVER:
            driver = chrome(wd / "chromium-profile")
            driver.set_page_load_timeout(30)
            driver.get(f"http://127.0.0.1:{http_port}/")
        yield {"driver": driver, "sitl": sitl, "recorder": recorder, "web": web, "workdir": wd}
    finally:
        stop_other.set()
        other.join(10)
        if driver is not None:
            driver.quit()
        if sitl.daemon is not None:
            sitl.stop()
        if recorder is not None:
            recorder.close()
        web.send_signal(signal.SIGTERM)
        try:
            web.wait(15)
        except subprocess.TimeoutExpired:
            web.kill()
            web.wait(5)


PAGE_STATE_JS = """
const card = document.querySelector(arguments[0]);
if (!card) return null;
const f = (n) => { const e = card.querySelector(`[data-field="${n}"]`); return e ? e.textContent : null; };
const h = card.querySelector('[data-field="heading_true_deg"]');
return {vehicle: f("vehicle"), status: f("status"), status_reason: f("status_reason"), link: f("link"),
        phase: f("phase"), autopilot: f("autopilot"), heading: h.textContent,
        heading_time_fc_s: h.dataset.time_fc_s || null, sigma: f("heading_sigma_deg"),
        counters: f("counters"), calibration: f("calibration"), fences: card.querySelectorAll(".track polygon.fence").length,
        events: card.querySelectorAll('[data-field="events"] li').length,
        sources: [...card.querySelectorAll('[data-field="sources"] tr[data-source]')].map(
          (r) => [r.dataset.source, ...[...r.cells].map((c) => c.textContent)])};
"""


def page(driver, vehicle: str = VEHICLE) -> dict | None:
    """What a vehicle's card shows, read in one script call (one instant of the live page)."""
    return driver.execute_script(PAGE_STATE_JS, f'section.vehicle[data-vehicle="{vehicle}"]')


def levelled(rec: ZenohRecorder) -> bool:
    return any(c["kind"] == "levelling" for c in rec.get("calibration"))


def test_page_shows_what_the_daemon_publishes(live):
    _browser_or_skip()
    d, rec, sitl = live["driver"], live["recorder"], live["sitl"]
    # WHEN the daemon has levelled on the launcher and has a heading (what the daemon itself
    # reports, waited for while the processes work: no timing luck)
    wait_live(live, lambda: levelled(rec), lambda: f"no levelling published; daemon log:\n{sitl.log('daemon')[-2000:]}")
    wait_live(live, lambda: (p := page(d)) and re.fullmatch(r"\d{1,3}\.\d°", p["heading"]),
              lambda: d.page_source[:3000])
    wait_live(live, lambda: page(d)["fences"] >= 1, "the fence was not drawn")
    wait_s = float(os.environ.get("AZIMUTHD_DASHBOARD_WAIT_S", "0"))
    if wait_s > 0:
        sitl.wait_for(lambda: False, wait_s)  # a longer flight for the documentation's screenshot

    # the page at one instant, and the heading payload the daemon published for the same FC time
    def shown_and_published():
        p = page(d)
        t_fc = p["heading_time_fc_s"]
        match = [h for h in rec.get("heading") if t_fc and h["time_fc_s"] == float(t_fc)]
        return (p, match[-1]) if match and p["heading"].endswith("°") else None
    pair = wait_live(live, shown_and_published, "the heading on the page matches no heading payload the daemon published")
    shown, published = pair

    # THEN the vehicle, by name, alive, link up, in the phase the daemon published
    assert shown["vehicle"] == VEHICLE
    assert shown["status"] == "alive" and shown["link"] == "up"
    assert shown["phase"] in ("pre-launch", "launch", "in-flight")
    assert shown["phase"] in {a["phase"] for a in rec.get("attitude")[-40:]}
    # the heading, to its display's rounding, and its sigma
    assert published["heading_valid"] is True
    assert abs(float(shown["heading"].rstrip("°")) - published["heading_true_deg"]) <= HEADING_DISPLAY_TOL_DEG
    assert shown["sigma"] == f"± {published['heading_sigma_deg']:.1f}° (1σ)"
    # the sources of that same payload: every one shown, used as reported, a reason when unused
    rows = {name: (used, why) for name, _, used, why in shown["sources"]}
    assert set(rows) == set(published["sources"])
    assert set(rows) == {"azimuth", "synthetic_ahrs", "heading_filter", "fc", "deviation"}  # every source reports
    for name, s in published["sources"].items():
        assert rows[name][0] == ("yes" if s["fused"] else "no"), name
        if not s["fused"]:
            assert rows[name][1] == s["detail"] and s["detail"] and s["why_not"], name
    assert set(published["heading_source"].split("+")) <= {n for n, (u, _) in rows.items() if u == "yes"} | {"coast"}
    # the second vehicle on the same page, in its own card, in name order
    other = page(d, OTHER)
    assert other["vehicle"] == OTHER and other["status"] == "alive"
    assert other["heading"] == f"{OTHER_HEADING_DEG:.1f}°" and other["sigma"] == "± 2.0° (1σ)"
    assert d.execute_script("return [...document.querySelectorAll('section.vehicle')].map(s => s.dataset.vehicle)") \
        == [VEHICLE, OTHER]
    # health counters and events came through
    assert shown["autopilot"] == "ardupilot"
    assert "imu samples" in shown["counters"]
    assert shown["events"] >= 1

    # no script error in the page
    errors = [e for e in d.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors

    # a browser that connects later (a reload) is given the picture at once: the heading, the
    # track's fence, the levelling and the events before it connected
    d.refresh()
    wait_live(live, lambda: (p := page(d)) and p["heading"].endswith("°") and p["fences"] >= 1
              and "levelling" in p["calibration"] and p["events"] >= 1 and p, lambda: str(page(d)))

    d.save_screenshot(str(live["workdir"] / "dashboard.png"))
    if os.environ.get("AZIMUTHD_DASHBOARD_PNG"):  # the whole page: both vehicles
        d.set_window_size(1500, d.execute_script("return document.body.scrollHeight") + 140)
        d.save_screenshot(os.environ["AZIMUTHD_DASHBOARD_PNG"])


def test_every_topic_published_validates_and_carries_wall_clock(live):
    rec, sitl = live["recorder"], live["sitl"]
    wait_live(live, lambda: levelled(rec), lambda: f"no levelling published:\n{sitl.log('daemon')[-2000:]}")
    wait_live(live, lambda: any("inclusion_polygons_deg" in g for g in rec.get("geofence")), "no fence published")
    # air_data at 2 Hz from method B's air data; calibration on change (levelling at least)
    for topic in ("attitude", "heading", "azimuth", "air_data", "calibration", "geofence", "health", "events"):
        payloads = rec.get(topic)
        assert payloads, f"nothing published on {topic}"
        for p in payloads:
            assert schema.validate(topic, p) == [], (topic, schema.validate(topic, p)[:3])
            assert isinstance(p["time_unix_s"], float) and p["time_unix_s"] > 1.7e9
    level = next(c for c in rec.get("calibration") if c["kind"] == "levelling")
    assert level["status"] == "done" and len(level["gyro_bias_rad_s"]) == 3
    air = rec.get("air_data")[-1]
    assert 300.0 < air["pressure_altitude_m"] < 500.0  # the launch site is at about 400 m
    fence = next(g for g in rec.get("geofence") if "inclusion_polygons_deg" in g)
    assert len(fence["inclusion_polygons_deg"][0]) == 4


def test_page_shows_the_daemon_gone_when_it_stops(live):
    _browser_or_skip()
    d, sitl = live["driver"], live["sitl"]
    sitl.daemon.send_signal(signal.SIGTERM)
    sitl.daemon.wait(HANG_S)
    wait_live(live, lambda: page(d)["status"] == "GONE", lambda: str(page(d)))
    shown = page(d)
    assert "liveliness token withdrawn" in shown["status_reason"]
    assert shown["link"] == "-"  # not the last "up" of a daemon that is gone
