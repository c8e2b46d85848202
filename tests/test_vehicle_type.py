"""``[launch] vehicle = "auto"``: the take-off model from the FC's HEARTBEAT and take-off parameters
(service/vehicle_type.py), and through the daemon's own Pipeline."""
import math

import numpy as np
import pytest

from mavlink_io.samples import FcHeartbeat, ImuSample, PressureSample
from service.config import validate
from service.pipeline import Pipeline
from service.vehicle_type import VehicleResolver, choose_vehicle, param_names
from sim.offline import simulate

ARDUPLANE_STOCK = {"Q_ENABLE": 0.0, "TKOFF_THR_MINACC": 0.0}   # plane.parm, read from ArduPlane SITL 4.7


@pytest.mark.parametrize("mav_type, vehicle", [(2, "multicopter"), (3, "multicopter"), (4, "multicopter"),
                                               (13, "multicopter"), (14, "multicopter"), (15, "multicopter"),
                                               (29, "multicopter"), (35, "multicopter"), (43, "multicopter"),
                                               (19, "vtol"), (20, "vtol"), (21, "vtol"), (22, "vtol"), (23, "vtol"),
                                               (24, "vtol"), (25, "vtol"), (47, "vtol"), (9, "launcher")])
def test_the_heartbeat_type_alone_decides_rotorcraft_vtol_and_rocket(mav_type, vehicle):
    for autopilot in ("ardupilot", "px4", "other"):
        ch = choose_vehicle(mav_type, autopilot, {})
        assert ch.vehicle == vehicle and ch.reason.startswith(f"HEARTBEAT type {mav_type} (")


@pytest.mark.parametrize("autopilot, params, vehicle, words", [
    ("ardupilot", ARDUPLANE_STOCK, "runway", "Q_ENABLE 0, TKOFF_THR_MINACC 0: a runway take-off"),
    ("ardupilot", {"Q_ENABLE": 1.0, "TKOFF_THR_MINACC": 0.0}, "vtol", "Q_ENABLE 1 (a QuadPlane)"),
    ("ardupilot", {"Q_ENABLE": 0.0, "TKOFF_THR_MINACC": 15.0}, "launcher", "TKOFF_THR_MINACC 15 m/s^2"),
    ("ardupilot", {}, "runway", "(Q_ENABLE, TKOFF_THR_MINACC not answered): a runway take-off"),
    ("px4", {"FW_LAUN_DETCN_ON": 1.0}, "launcher", "FW_LAUN_DETCN_ON 1"),
    ("px4", {"FW_LAUN_DETCN_ON": 0.0}, "runway", "FW_LAUN_DETCN_ON 0: a runway take-off"),
    ("other", {}, "runway", "HEARTBEAT type 1 (fixed wing, other): a runway take-off"),
])
def test_a_fixed_wing_takes_off_as_its_own_parameters_say(autopilot, params, vehicle, words):
    ch = choose_vehicle(1, autopilot, params)
    assert ch.vehicle == vehicle
    assert words in ch.reason, ch.reason


def test_a_vehicle_that_does_not_fly_has_no_take_off_model():
    ch = choose_vehicle(10, "ardupilot", {})   # ground rover
    assert ch.vehicle is None and ch.reason == "HEARTBEAT type 10 has no take-off model: set [launch] vehicle"


def test_configured_values_are_used_as_configured():
    r = VehicleResolver("hand")
    assert not r.pending and r.choice.vehicle == "hand" and r.choice.reason == "configured"
    assert r.on_heartbeat(2, "ardupilot", 0.0) is None and r.choice.vehicle == "hand"


def test_auto_waits_for_the_heartbeat_and_for_a_fixed_wings_parameters():
    """GIVEN auto WHEN nothing came from the FC THEN nothing is chosen; WHEN a fixed wing's HEARTBEAT
    came THEN it waits for its take-off parameters, decides once they are all answered, and never again."""
    r = VehicleResolver("auto", params_wait_s=5.0)
    assert r.pending and r.poll(100.0) is None
    assert r.on_heartbeat(1, "ardupilot", 10.0) is None and r.pending
    assert r.on_params({"Q_ENABLE": 0.0}, False, 10.5) is None and r.pending   # one of two answered
    ch = r.on_params({"Q_ENABLE": 0.0, "TKOFF_THR_MINACC": 15.0, "EK2_ENABLE": 0.0}, False, 10.6)
    assert ch.vehicle == "launcher" and not r.pending
    assert r.on_params({"Q_ENABLE": 1.0}, True, 11.0) is None and r.choice.vehicle == "launcher"
    assert param_names("ardupilot") == ("Q_ENABLE", "TKOFF_THR_MINACC") and param_names(None) == ()


def test_auto_decides_without_parameters_the_fc_never_answered():
    r = VehicleResolver("auto", params_wait_s=5.0)
    r.on_heartbeat(1, "ardupilot", 10.0)
    assert r.poll(14.9) is None
    assert r.poll(15.0).vehicle == "runway"            # given up: a log replayed without parameters
    r2 = VehicleResolver("auto", params_wait_s=5.0)
    r2.on_heartbeat(1, "ardupilot", 10.0)
    assert r2.on_params({}, True, 11.0).vehicle == "runway"   # the link gave up asking
    r3 = VehicleResolver("auto")
    assert r3.on_heartbeat(2, "px4", 0.0).vehicle == "multicopter"   # a copter waits for nothing


# --- through the Pipeline ----------------------------------------------------------------------------

RATE_HZ = 50.0


@pytest.fixture(scope="module")
def runway_run():
    """ArduPlane's runway take-off at its 50 Hz (sim/scenarios/runway_takeoff), 17 s."""
    return simulate("runway_takeoff", seed=2, imu_rate_hz=RATE_HZ, duration_s=17.0)


def _feed(run, heartbeat_type: int | None, params: dict | None):
    """The run's IMU and baro samples to a Pipeline on the shipped default (vehicle auto); an
    ArduPilot HEARTBEAT (armed) at 1 Hz from 0.5 s of type ``heartbeat_type`` (None: no FC heard),
    its parameters answered at 1.0 s. Returns (pipeline, [(time_s, kind, detail)])."""
    items = [(t, 2, ImuSample(t, t, g.copy(), a.copy(), m.copy(), "RAW_IMU", 0))
             for t, g, a, m in zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss)]
    items += [(t, 1, PressureSample(t, t, p, d, k)) for t, p, d, k in
              zip(run.baro_time_s.tolist(), run.press_abs_pa.tolist(), run.press_diff_pa.tolist(),
                  run.temperature_k.tolist())]
    if heartbeat_type is not None:
        items += [(t, -1, FcHeartbeat(t, 1, 1, "ardupilot", heartbeat_type, 129, 0, 3, True))
                  for t in np.arange(0.5, run.time_s[-1], 1.0).tolist()]
    if params is not None:
        items.append((1.0, -2, params))
    items.sort(key=lambda x: (x[0], x[1]))
    s = run.site
    p = Pipeline(validate({"site": {"lat_deg": s["lat_deg"], "lon_deg": s["lon_deg"], "alt_m": s["alt_m"],
                                    "decimal_year": s["decimal_year"]},
                           "mavlink": {"imu_rate_hz": RATE_HZ}, "launch": {"case": "aligned"},
                           "azimuth": {"solve_in_background": False}}))
    assert p.vehicle.configured == "auto"   # the shipped default
    events = []
    for t, _o, it in items:
        if isinstance(it, ImuSample):
            p.on_imu(it)
        elif isinstance(it, PressureSample):
            p.on_pressure(it)
        elif isinstance(it, FcHeartbeat):
            p.on_fc_heartbeat(it)
        else:
            p.on_fc_params(it, True, t)
        events += [(t, k, d) for k, d in p.drain_events()]
    return p, events


def test_pipeline_auto_takes_arduplanes_runway_take_off_from_its_heartbeat(runway_run):
    """GIVEN the shipped default (vehicle auto) and ArduPlane's HEARTBEAT (fixed wing) with its stock
    take-off parameters WHEN it rolls down the runway THEN the Pipeline says once which take-off model
    and why, and detects the take-off roll as configured "runway" does (within 0.3 s of the true one)."""
    p, events = _feed(runway_run, 1, ARDUPLANE_STOCK)
    chosen = [(t, d) for t, k, d in events if k == "vehicle"]
    assert chosen == [(1.0, "runway take-off (auto): HEARTBEAT type 1 (fixed wing, ardupilot), Q_ENABLE 0, "
                            "TKOFF_THR_MINACC 0: a runway take-off")]
    takeoff = [d for _t, k, d in events if k == "takeoff"]
    assert len(takeoff) == 1 and takeoff[0].startswith("runway: forward specific force"), takeoff
    assert abs(p.phase.launch_time_s - runway_run.truth.launch_time_s) < 0.3


def test_pipeline_auto_declares_no_take_off_before_the_fc_has_said(runway_run):
    """GIVEN vehicle auto and no FC heard WHEN the same take-off roll happens THEN it still levels,
    and no take-off is declared (no model to judge it by)."""
    p, events = _feed(runway_run, None, None)
    assert "levelled" in [k for _t, k, _d in events] and not math.isnan(p.phase.level.roll_rad)
    assert not [k for _t, k, _d in events if k in ("takeoff", "vehicle", "started_in_flight")]
    assert p.phase.launch_time_s is None and p.vehicle.pending


# --- through the daemon's wiring ---------------------------------------------------------------------

class _Link:
    """What the daemon's parameter reading and health flags need from MavlinkLink."""

    def __init__(self):
        self.fc_autopilot = "ardupilot"
        self.fc_params, self.fc_params_missing, self.asked = {}, set(), []
        self.rate_advice = None

    def read_params(self, names):
        self.asked.append(tuple(names))

    def stream_report(self):
        return {}


def test_daemon_reads_the_take_off_parameters_and_shows_its_choice_on_health(tmp_path):
    """GIVEN the daemon on the shipped default WHEN ArduPilot is detected THEN it asks for Q_ENABLE and
    TKOFF_THR_MINACC with the heading-feed parameters; WHEN a fixed wing's HEARTBEAT came THEN health says
    it waits; WHEN the parameters are read (TKOFF_THR_MINACC 15: a catapult) THEN health says launcher and why."""
    from mavlink_io.link import LinkEvent
    from service.daemon import Daemon
    d = Daemon(validate({"site": {"lat_deg": 47.0, "lon_deg": 8.0}, "zenoh": {"enabled": False},
                         "service": {"state_dir": str(tmp_path)}, "azimuth": {"solve_in_background": False}}))
    try:
        d.link = link = _Link()
        d.dispatch(LinkEvent("autopilot_detected", "ardupilot", 1.0))
        assert {"Q_ENABLE", "TKOFF_THR_MINACC", "VISO_TYPE", "EK2_ENABLE"} <= set(link.asked[-1])
        d.dispatch(FcHeartbeat(1.1, 1, 1, "ardupilot", 1, 81, 0, 3, False))
        assert d._health_flags()["vehicle"] == "not known yet (auto: waiting for the FC)"
        link.fc_params = {"Q_ENABLE": 0.0, "TKOFF_THR_MINACC": 15.0, "VISO_TYPE": 0.0}
        d.dispatch(LinkEvent("params_read", "Q_ENABLE 0, TKOFF_THR_MINACC 15, VISO_TYPE 0", 1.5))
        assert d._health_flags()["vehicle"] == ("launcher: HEARTBEAT type 1 (fixed wing, ardupilot), "
                                                "TKOFF_THR_MINACC 15 m/s^2 (a hand/catapult launch)")
        assert d.pipeline.phase_params.vehicle == "launcher"
    finally:
        d.pipeline.solver.close()
