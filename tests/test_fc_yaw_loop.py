"""The ODOMETRY loop and the placeholder hazard, decided from the FC's own parameters.

Against ArduPlane SITL (issue 15): EKF3 fused our ODOMETRY yaw (EK3_SRC1_YAW 6) while the daemon kept
trusting the FC's yaw, its own (a loop: EKF3's yaw after the GNSS cut 3.80 deg RMS against 1.08 with
its compass); and EKF2, which ArduPlane runs by default (EK2_ENABLE 1), fused the placeholder
position ("EKF2 IMU0 is using external nav data"). Now the daemon reads the parameters before any
ODOMETRY, sends none while an estimator could fuse the placeholder, stops for good if the FC says one
did, and excludes the FC's yaw everywhere once it is ours."""
from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.fc_yaw_feed import ARDUPILOT_PARAMS, check_fc_yaw_feed
from mavlink_io.link import LinkConfig, MavlinkLink
from mavlink_io.outputs import OutputScheduler
from service.fc_yaw_guard import FcYawGuard
from sim.autopilot import Autopilot
from mem_transport import MemTransport
from test_ardupilot_rates import SimLoop

# ArduPlane 4.7 SITL as shipped (read with PARAM_REQUEST_READ): EKF2 on, VISO off, compass yaw
STOCK = {"VISO_TYPE": 0, "EK2_ENABLE": 1, "EK3_ENABLE": 1} | {
    f"EK3_SRC{n}_{k}": v for n, src in ((1, (3, 3, 1, 3, 1)), (2, (0, 0, 1, 0, 0)), (3, (0, 0, 1, 0, 0)))
    for k, v in zip(("POSXY", "VELXY", "POSZ", "VELZ", "YAW"), src)}
# what issue 15's SITL run set to have our yaw fused, plus the fix: EK2_ENABLE 0
OURS = STOCK | {"VISO_TYPE": 1, "EK3_SRC1_YAW": 6, "EK2_ENABLE": 0}


def test_stock_ardupilot_ignores_odometry_and_its_yaw_is_independent():
    c = check_fc_yaw_feed("ardupilot", STOCK, set())
    assert c.placeholder_safe is True and c.fc_yaw_from_us is False and "VISO_TYPE 0" in c.reason


def test_ekf2_running_makes_the_placeholder_unsafe_and_names_the_parameter():
    c = check_fc_yaw_feed("ardupilot", OURS | {"EK2_ENABLE": 1}, set())
    assert c.placeholder_safe is False and "set EK2_ENABLE 0" in c.reason and "not sent" in c.reason


def test_ekf3_external_nav_position_in_any_source_set_is_unsafe():
    for name in ("EK3_SRC1_POSXY", "EK3_SRC2_VELXY", "EK3_SRC3_POSZ", "EK3_SRC2_VELZ"):
        c = check_fc_yaw_feed("ardupilot", OURS | {name: 6}, set())
        assert c.placeholder_safe is False and f"set {name} to another source" in c.reason, name


def test_ekf3_yaw_from_us_is_the_loop():
    c = check_fc_yaw_feed("ardupilot", OURS, set())
    assert c.placeholder_safe is True and c.fc_yaw_from_us is True and "EK3_SRC1_YAW 6" in c.reason
    c2 = check_fc_yaw_feed("ardupilot", OURS | {"EK3_SRC1_YAW": 1, "EK3_SRC2_YAW": 6}, set())
    assert c2.fc_yaw_from_us is True  # a set the pilot can switch to in flight counts too


def test_unreadable_or_pending_parameters():
    assert check_fc_yaw_feed("ardupilot", {"VISO_TYPE": 1}, set()).placeholder_safe is None
    no_src = {k: v for k, v in OURS.items() if not k.startswith("EK3_SRC")}
    c = check_fc_yaw_feed("ardupilot", no_src, {k for k in ARDUPILOT_PARAMS if k.startswith("EK3_SRC")})
    assert c.placeholder_safe is False and "cannot verify" in c.reason
    # no EK2_ENABLE on this firmware (built without EKF2): nothing else fuses the placeholder
    no_ek2 = {k: v for k, v in OURS.items() if k != "EK2_ENABLE"}
    assert check_fc_yaw_feed("ardupilot", no_ek2, {"EK2_ENABLE"}).placeholder_safe is True


def test_px4_ev_ctrl():
    assert check_fc_yaw_feed("px4", {"EKF2_EV_CTRL": 8}, set()).fc_yaw_from_us is True
    c = check_fc_yaw_feed("px4", {"EKF2_EV_CTRL": 9}, set())
    assert c.placeholder_safe is False and "EKF2_EV_CTRL 8" in c.reason
    assert check_fc_yaw_feed("px4", {"EKF2_EV_CTRL": 0}, set()).fc_yaw_from_us is False
    assert check_fc_yaw_feed("other", {}, set()).placeholder_safe is True  # NaN position there


def test_px4_ev_ctrl_decides_without_the_older_names():
    """A PX4 >= 1.14 answers EKF2_EV_CTRL: the verdict does not wait for EKF2_AID_MASK / EKF2_HGT_MODE,
    which it will never answer."""
    c = check_fc_yaw_feed("px4", {"EKF2_EV_CTRL": 8}, set())
    assert c.placeholder_safe is True and c.fc_yaw_from_us is True
    assert check_fc_yaw_feed("px4", {}, set()).placeholder_safe is None          # still reading


def test_px4_aid_mask_before_1_14():
    """PX4 <= 1.13 has no EKF2_EV_CTRL: EKF2_AID_MASK bits 3 (vision position) and 8 (vision velocity)
    must be off, EKF2_HGT_MODE not 3 (vision height); bit 4 (vision yaw) means the FC's yaw is ours."""
    gone = {"EKF2_EV_CTRL"}
    waiting = check_fc_yaw_feed("px4", {"EKF2_AID_MASK": 16}, gone)
    assert waiting.placeholder_safe is None and "EKF2_HGT_MODE" in waiting.reason
    c = check_fc_yaw_feed("px4", {"EKF2_AID_MASK": 1 | 16, "EKF2_HGT_MODE": 0}, gone)
    assert c.placeholder_safe is True and c.fc_yaw_from_us is True and "1.13" in c.reason
    c = check_fc_yaw_feed("px4", {"EKF2_AID_MASK": 1, "EKF2_HGT_MODE": 0}, gone)
    assert c.placeholder_safe is True and c.fc_yaw_from_us is False
    c = check_fc_yaw_feed("px4", {"EKF2_AID_MASK": 1 | 8 | 16, "EKF2_HGT_MODE": 0}, gone)   # vision position
    assert c.placeholder_safe is False and c.fc_yaw_from_us is True and "EKF2_AID_MASK 17" in c.reason
    c = check_fc_yaw_feed("px4", {"EKF2_AID_MASK": 16 | 256, "EKF2_HGT_MODE": 0}, gone)     # vision velocity
    assert c.placeholder_safe is False and "EKF2_AID_MASK 16" in c.reason
    c = check_fc_yaw_feed("px4", {"EKF2_AID_MASK": 16, "EKF2_HGT_MODE": 3}, gone)           # vision height
    assert c.placeholder_safe is False and "EKF2_HGT_MODE 3" in c.reason
    c = check_fc_yaw_feed("px4", {}, {"EKF2_EV_CTRL", "EKF2_AID_MASK", "EKF2_HGT_MODE"})
    assert c.placeholder_safe is False and c.fc_yaw_from_us is None and "cannot verify" in c.reason


def test_no_odometry_while_not_allowed():
    from test_outputs_rates import solution
    sched = OutputScheduler()
    sched.odometry_allowed = False
    assert 331 not in {m.get_msgId() for m in sched.messages(solution(), 0.0)}
    sched.odometry_allowed = True
    assert 331 in {m.get_msgId() for m in sched.messages(solution(t_fc=11.0), 1.0)}


def test_the_fc_saying_it_uses_external_nav_stops_odometry_for_good():
    g = FcYawGuard()
    g.start("ardupilot")
    g.on_params(OURS, set())
    assert g.odometry_allowed
    assert g.on_statustext("EKF2 IMU0 is using external nav data", odometry_sent=False) == []  # not ours
    (ev,) = g.on_statustext("EKF2 IMU0 is using external nav data", odometry_sent=True)
    assert ev[0] == "placeholder_fused" and ev[1] == "error" and "set EK2_ENABLE 0" in ev[2]
    assert not g.odometry_allowed
    g.on_params(OURS, set())  # even parameters that look safe do not undo a fused placeholder
    assert not g.odometry_allowed and g.flags()["odometry"].startswith("stopped")


# --- the daemon against the simulator (ardupilot personality), in memory ---------------------

def daemon_on_sim(tmp_path, params: dict | None = None, seed: int = 2):
    """A Daemon (inline solver, 25 Hz IMU) wired in memory to the simulator's ArduPilot
    personality: (autopilot, daemon, loop, events); its events are collected, not logged."""
    from service.config import validate
    from service.daemon import Daemon
    ap = Autopilot("runway_gnss_denied", "udpout:127.0.0.1:9", personality="ardupilot", seed=seed)
    ap.params.update({k: float(v) for k, v in (params or {}).items()})
    cfg = validate({"site": {"lat_deg": 47.0, "lon_deg": 8.0}, "zenoh": {"enabled": False},
                    "service": {"state_dir": str(tmp_path)}, "azimuth": {"solve_in_background": False},
                    "mavlink": {"imu_rate_hz": 25.0, "pressure_rate_hz": 10.0, "attitude_rate_hz": 10.0}})
    d = Daemon(cfg, clock=lambda: ap.t)
    loop = SimLoop(ap, d.link_cfg.stream_rates_hz)
    d.link = loop.link
    events = []
    d._event = lambda kind, detail: events.append((kind, detail))
    return ap, d, loop, events


def _daemon_against_sim(tmp_path, params: dict, until_s: float = 3.0):
    ap, d, loop, events = daemon_on_sim(tmp_path, params)
    while ap.t < until_s:
        loop.run(ap.t + 0.05)
        for it in loop.items:
            d.dispatch(it)
        loop.items.clear()
        d._publish_due(ap.t)
    return d, events


def test_daemon_reads_the_parameters_and_excludes_its_own_yaw(tmp_path):
    # GIVEN an ArduPilot whose EKF3 takes its yaw from our ODOMETRY, EKF2 off
    d, events = _daemon_against_sim(tmp_path, OURS)
    # THEN the FC's yaw is no reference anywhere, ODOMETRY is allowed, and health says why
    assert d.fc_yaw_guard.check.fc_yaw_from_us is True
    assert d.pipeline.use_fc_yaw is False
    assert any(k == "fc_yaw_excluded" for k, _ in d.pipeline.drain_events() + events)
    assert d.scheduler.odometry_allowed is True
    flags = d._health_flags()
    assert flags["fc_yaw"].startswith("not a reference") and flags["odometry"] == "allowed"
    d.pipeline.solver.close()


def test_daemon_refuses_odometry_while_ekf2_runs(tmp_path):
    d, _ = _daemon_against_sim(tmp_path, OURS | {"EK2_ENABLE": 1})
    assert d.scheduler.odometry_allowed is False
    assert "set EK2_ENABLE 0" in d._health_flags()["odometry"]
    assert d.pipeline.use_fc_yaw is True  # nothing of ours reaches its EKF: its yaw stays its own
    d.pipeline.solver.close()


def test_param_reader_resends_the_unanswered_and_gives_up_on_unknown_names():
    from mavlink_io.params import ParamReader
    r = ParamReader(timeout_s=1.0, max_tries=3)
    assert r.start(["EK2_ENABLE", "VISO_TYPE"], 0.0) == ["EK2_ENABLE", "VISO_TYPE"]
    assert r.on_value("VISO_TYPE", 1.0) and not r.on_value("SYSID_THISMAV", 1.0)  # not watched
    assert r.poll(0.9) == [] and r.poll(1.0) == ["EK2_ENABLE"]  # only the unanswered one again
    assert r.poll(2.0) == ["EK2_ENABLE"] and not r.done
    assert r.poll(3.0) == [] and r.done and r.missing == {"EK2_ENABLE"}  # 3 tries: not on this firmware
    assert r.values == {"VISO_TYPE": 1.0}
    r.on_value("EK2_ENABLE", 0.0)  # a late or unsolicited PARAM_VALUE still counts
    assert r.missing == set() and r.values["EK2_ENABLE"] == 0.0


def test_replay_reads_px4_1_13_parameters():
    """A ULog of PX4 <= 1.13 whose EKF2_AID_MASK fuses vision yaw: replay excludes the FC's yaw by itself."""
    from service.logreaders import LogSummary
    from service.replay import fc_yaw_from_our_odometry
    why = fc_yaw_from_our_odometry(LogSummary("ulog", "px4", params={"EKF2_AID_MASK": 17.0, "EKF2_HGT_MODE": 0.0}))
    assert why is not None and "yaw comes from our ODOMETRY" in why
    assert fc_yaw_from_our_odometry(LogSummary("ulog", "px4", params={"EKF2_AID_MASK": 1.0,
                                                                      "EKF2_HGT_MODE": 0.0})) is None
