"""service/geofence.py: breach prediction, uncertainty margin, latch/hysteresis, actions (synthetic inputs).

GIVEN/WHEN/THEN with exactly known inputs: a vehicle dead-reckoned from the launch site at a
constant heading and airspeed; the expected breach times follow from the geometry.
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from estimators.dead_reckoning import DrParams
from estimators.geodesy import LocalGnomonic, inside_polygon, vincenty_direct
from mavlink_io.commands import CommandOutcome
from service.geofence import GeofenceMonitor, corridor_polygon
from service.geofence_config import validate_geofence

HOME = (47.3, 8.5, 450.0)
HALF = 2000.0
ONE_UPDATE = 0.101
"""Expected times are exact up to one 10 Hz update (a tie at the exact threshold goes either way)."""


def square(half=HALF, centre=HOME):
    lat0, lon0 = math.radians(centre[0]), math.radians(centre[1])
    out = []
    for az in (45.0, 135.0, 225.0, 315.0):
        la, lo = vincenty_direct(lat0, lon0, math.radians(az), half * math.sqrt(2))
        out.append([math.degrees(la), math.degrees(lo)])
    return out


def monitor(dr_params=DrParams(sideslip_sigma_rad=0.0), **kw):
    raw = {"enabled": True, "inclusion": [square()], "margin_m": 50.0, "sigma_k": 2.0, "lookahead_s": 20.0,
           "trigger_hold_s": 0.5, "wind_source": "config", "wind_sigma_m_s": 0.0, "tas_sigma_m_s": 0.0,
           "fix_sigma_m": 0.0, "update_hz": 10.0, "clear_distance_m": 200.0, "clear_hold_s": 5.0,
           "actions": ["rtl", "rtl_mode"]}
    raw.update(kw)
    m = GeofenceMonitor(validate_geofence(raw), *HOME, dr_params=dr_params)
    m.on_heartbeat(SimpleNamespace(armed=True, autopilot="ardupilot", vehicle_type=1))
    return m


def air(t, tas=20.0, alt_rel=100.0, rate=0.0):
    return SimpleNamespace(time_s=t, pressure_altitude_m=1000.0 + alt_rel, pitot_blocked=False, pitot_noisy=False,
                           tas_m_s=tas, tas_noise_std_m_s=0.0, alt_rate_m_s=rate, rate_valid=True)


def sol(t, heading_deg, sigma_deg=0.0, phase="in-flight", valid=True):
    return SimpleNamespace(time_fc_s=t, phase=phase, heading_valid=valid, heading_rad=math.radians(heading_deg) % (2 * math.pi),
                           heading_sigma_rad=math.radians(sigma_deg))


def run(m, t0, t1, heading_deg, sigma_deg=0.0, tas=20.0, alt_rel=100.0, rate=0.0, dt=0.1, valid=True):
    cmds = []
    t = t0
    while t < t1 - 1e-9:
        t = round(t + dt, 6)
        cmds += [(t, c) for c in m.step(sol(t, heading_deg, sigma_deg, valid=valid), air(t, tas, alt_rel + rate * (t - t0), rate), t)]
    return cmds


def prelaunch(m):
    m.step(sol(0.0, 90.0, phase="pre-launch"), air(0.0, 0.0, 0.0), 0.0)   # baro reference at the launch site


def test_predicted_breach_time_exact_without_uncertainty():
    # GIVEN 20 m/s due east from the launch site, 2000 m from the east edge, margin 50 m, look-ahead 20 s
    m = monitor()
    prelaunch(m)
    cmds = run(m, 0.0, 100.0, 90.0)
    # THEN (dead reckoning starts at the first in-flight update, t = 0.1 s) the breach is first
    # predicted when 2000 - 20 (t - 0.1) - 50 <= 20 * 20  -> t = 77.6 s, latched 0.5 s later,
    # and RTL is sent once
    ev = {e.kind: e for e in m.drain_events()}
    assert ev["geofence_warning"].time_fc_s == pytest.approx(77.6, abs=ONE_UPDATE)
    assert ev["geofence_breach"].time_fc_s == pytest.approx(78.1, abs=ONE_UPDATE)
    assert [c.name for _, c in cmds] == ["rtl"] and cmds[0][0] == pytest.approx(78.1, abs=ONE_UPDATE)
    assert cmds[0][1].command == 20
    assert m.state()["state"] == "breach" and m.state()["time_to_breach_s"] is not None


def rectangle(north_m, south_m, half_east_m):
    """Corners north/south of the launch site (geodesics), the east/west edges half_east_m away."""
    lat0, lon0 = math.radians(HOME[0]), math.radians(HOME[1])
    out = []
    for n_m, e_m in ((north_m, half_east_m), (-south_m, half_east_m), (-south_m, -half_east_m), (north_m, -half_east_m)):
        la, lo = vincenty_direct(lat0, lon0, math.atan2(e_m, n_m), math.hypot(n_m, e_m))
        out.append([math.degrees(la), math.degrees(lo)])
    return out


def test_divert_when_the_fence_is_inside_the_uncertainty_not_only_the_mean():
    # GIVEN a fence edge 300 m north of the launch site (10 km long) and a flight due east along it
    # with a 3 deg heading sigma (a bias over the flight: tau_heading 1e6 s)
    params = DrParams(sideslip_sigma_rad=0.0, tau_heading_s=1e6)

    def fly(k):
        m = monitor(dr_params=params, sigma_k=k, inclusion=[rectangle(300.0, 2000.0, 10000.0)], update_hz=5.0)
        prelaunch(m)
        return m, run(m, 0.0, 200.0, 90.0, sigma_deg=3.0, dt=0.2)
    m2, cmds2 = fly(2.0)
    m0, cmds0 = fly(0.0)
    # WHEN the mean never gets closer than ~300 m to the north edge (it flies parallel to it)
    # THEN with k = 2 the cross-track sigma V sigma_psi (t - 0.1 + 20) reaches (300 - 50) / 2 m at
    # t = 125 / (20 * 0.05236) - 19.8 = 99.6 s (the geodesic edge bows ~8 m: +-0.5 s; 5 Hz updates),
    # latched 0.5 s later
    assert [c.name for _, c in cmds2] == ["rtl"]
    assert cmds2[0][0] == pytest.approx(100.1, abs=0.7)
    ev = [e for e in m2.drain_events() if e.kind == "geofence_breach"][0]
    assert 280.0 < ev.fields["distance_to_fence_m"] < 310.0  # the mean was still ~300 m inside
    # AND with k = 0 (mean only) the same flight never diverts
    assert cmds0 == []


def test_no_action_while_disarmed_then_sent_when_armed():
    m = monitor()
    m.on_heartbeat(SimpleNamespace(armed=False, autopilot="ardupilot", vehicle_type=1))
    prelaunch(m)
    cmds = run(m, 0.0, 85.0, 90.0)
    assert cmds == [] and m.latched
    kinds = [e.kind for e in m.drain_events()]
    assert "geofence_no_action" in kinds
    m.on_heartbeat(SimpleNamespace(armed=True, autopilot="ardupilot", vehicle_type=1))
    cmds = run(m, 85.0, 86.0, 90.0)
    assert [c.name for _, c in cmds] == ["rtl"]


def test_disabled_by_command_predicts_but_does_not_act_until_enabled():
    """MAV_CMD_DO_FENCE_ENABLE 0 to our component (service/command_server.py): dead reckoning and
    prediction go on, the breach latches and is reported, no divert is sent; enabled again, the
    first action goes out at the next update."""
    m = monitor()
    m.actions_enabled = False
    prelaunch(m)
    cmds = run(m, 0.0, 85.0, 90.0)
    assert cmds == [] and m.latched and m.dr is not None
    events = m.drain_events()
    assert any(e.kind == "geofence_no_action" and "disabled by command" in e.text for e in events)
    assert m.state()["action_status"] == "blocked: disabled by command"
    m.actions_enabled = True
    cmds = run(m, 85.0, 86.0, 90.0)
    assert [c.name for _, c in cmds] == ["rtl"]


def test_no_action_on_the_ground():
    m = monitor(inclusion=[square(half=100.0)])
    for k in range(50):
        assert m.step(sol(k * 0.1, 90.0, phase="pre-launch"), air(k * 0.1, 0.0, 0.0), k * 0.1) == []
    assert m.state()["state"] == "inactive"


def test_latch_clears_only_well_inside_after_the_hold():
    m = monitor()
    prelaunch(m)
    run(m, 0.0, 80.0, 90.0)
    assert m.latched
    m.on_command_outcome(CommandOutcome("rtl", 20, "accepted", 0, 1, 78.0, 78.2), 78.2)
    # turn back west: the breach is no longer predicted at once, but the latch holds
    cmds = run(m, 80.0, 81.0, 270.0)
    assert m.latched and cmds == []
    # clearance now = d - margin = (2000 - 20 t_east + 20 t_west) - 50 must exceed 200 m, held 5 s
    cmds = run(m, 81.0, 140.0, 270.0)
    clear = [e for e in m.drain_events() if e.kind == "geofence_clear"]
    assert len(clear) == 1 and cmds == []
    # at t=80 the vehicle is 1600 m east; clearance = 2000-1600-50 = 350 > 200 already; predicted-free
    # from the turn on: cleared at 80 + 0.1 + 5 s
    assert clear[0].time_fc_s == pytest.approx(85.1, abs=0.25)
    assert not m.latched and m.state()["action"] is None


def test_hysteresis_no_clear_when_only_marginally_inside():
    m = monitor(clear_distance_m=1000.0)
    prelaunch(m)
    run(m, 0.0, 80.0, 90.0)
    run(m, 80.0, 100.0, 0.0)   # fly north along the east side: never 1000 m clear
    assert m.latched
    assert not any(e.kind == "geofence_clear" for e in m.drain_events())


def test_denied_then_timeout_walks_the_action_list():
    m = monitor(actions=["rtl", "rtl_mode", "reposition"], safe_lat_deg=HOME[0], safe_lon_deg=HOME[1])
    prelaunch(m)
    cmds = run(m, 0.0, 80.0, 90.0)
    assert [c.name for _, c in cmds] == ["rtl"]
    nxt = m.on_command_outcome(CommandOutcome("rtl", 20, "denied", 3, 1, 78.0, 78.1), 78.1)
    assert [c.name for c in nxt] == ["rtl_mode"] and nxt[0].command == 176 and nxt[0].params[1] == 11.0
    nxt = m.on_command_outcome(CommandOutcome("rtl_mode", 176, "timeout", None, 5, 78.1, 83.1), 83.1)
    assert [c.name for c in nxt] == ["reposition"] and nxt[0].use_int
    assert nxt[0].params[4] == round(HOME[0] * 1e7)
    nxt = m.on_command_outcome(CommandOutcome("reposition", 192, "denied", 4, 1, 83.1, 83.2), 83.2)
    assert nxt == []
    assert any(e.kind == "geofence_no_action" and "every action" in e.text for e in m.drain_events())
    # an outcome for something else is ignored
    assert m.on_command_outcome(CommandOutcome("rates", 511, "denied", 4, 1, 0, 0), 84.0) == []


def test_escalation_to_termination_when_still_outside():
    m = monitor(actions=["rtl", "terminate"], allow_termination=True, escalate_after_s=10.0)
    prelaunch(m)
    cmds = run(m, 0.0, 80.0, 90.0)
    m.on_command_outcome(CommandOutcome("rtl", 20, "accepted", 0, 1, 78.0, 78.2), 78.2)
    # the vehicle ignores the RTL and keeps flying east: outside (mean) from t = 100 s on
    cmds = run(m, 80.0, 115.0, 90.0)
    names = [(round(t, 1), c.name) for t, c in cmds]
    # the mean crosses the east edge at t = 100.1 s; terminate 10 s later
    assert names == [(pytest.approx(110.1, abs=0.11), "terminate")]
    assert cmds[0][1].command == 185 and cmds[0][1].params[0] == 1.0


def test_exclusion_zone_ahead():
    # a 400 m exclusion square 1500 m north of the launch site
    lat0, lon0 = math.radians(HOME[0]), math.radians(HOME[1])
    la, lo = vincenty_direct(lat0, lon0, 0.0, 1700.0)
    ex = square(half=200.0, centre=(math.degrees(la), math.degrees(lo)))
    m = monitor(inclusion=[square(half=5000.0)], exclusion=[ex])
    prelaunch(m)
    cmds = run(m, 0.0, 60.0, 0.0)
    # its south edge is 1500 m ahead: 1500 - 50 - 20 (t - 0.1) <= 400 -> t = 52.6 s, +0.5 s hold
    assert [c.name for _, c in cmds] == ["rtl"] and cmds[0][0] == pytest.approx(53.1, abs=ONE_UPDATE)


def test_altitude_ceiling_predicted_with_the_climb_rate_and_floor_armed_after_climb():
    m = monitor(inclusion=[], alt_min_m=30.0, alt_max_m=300.0, alt_margin_m=10.0, alt_sigma_m=5.0)
    prelaunch(m)
    # climbing 5 m/s from 0 m: below the floor on the launcher, but the floor is not armed yet
    cmds = run(m, 0.0, 60.0, 90.0, alt_rel=0.0, rate=5.0)
    # ceiling: 300 - 5 t - 10 - 2 * 5 <= 5 * 20  -> t = 36 s, +0.5 s
    assert [c.name for _, c in cmds] == ["rtl"] and cmds[0][0] == pytest.approx(36.5, abs=ONE_UPDATE)
    m2 = monitor(inclusion=[], alt_min_m=30.0, alt_max_m=300.0, alt_margin_m=10.0, alt_sigma_m=5.0)
    prelaunch(m2)
    run(m2, 0.0, 10.0, 90.0, alt_rel=100.0)
    cmds = run(m2, 10.0, 40.0, 90.0, alt_rel=100.0, rate=-2.0)
    # floor: 100 - 2 t' - 30 - 10 - 10 <= 2 * 20 -> t' = 5 s after the descent starts (+0.5 s)
    assert cmds and cmds[0][0] == pytest.approx(15.5, abs=ONE_UPDATE)


def test_a_late_daemon_arms_the_floor_on_the_height_reached_not_the_predicted_one():
    # GIVEN a floor of 30 m (armed above 30 + 10 + 2 x 5 = 50 m; the ceiling far) and a daemon 5 s late from 1 s on,
    # the vehicle climbing at 10 m/s to 45 m and holding it
    m = monitor(inclusion=[], alt_min_m=30.0, alt_max_m=1000.0, alt_margin_m=10.0, alt_sigma_m=5.0)
    prelaunch(m)
    t, cmds = 0.0, []
    while t < 30.0 - 1e-9:
        t = round(t + 0.1, 6)
        h, rate = min(10.0 * t, 45.0), (10.0 if 10.0 * t < 45.0 else 0.0)
        cmds += m.step(sol(t, 90.0), air(t, alt_rel=h, rate=rate), t + (5.0 if t >= 1.0 else 0.0))
    # WHEN its prediction 5 s ahead of the climb passes 50 m (from t = 0.1 s) but the height never does
    # THEN the floor is never armed: no warning, no divert at 45 m
    assert m.input_age_s == pytest.approx(5.0)
    assert cmds == [] and not any(e.kind in ("geofence_warning", "geofence_breach") for e in m.drain_events())


def test_heading_unknown_grows_the_radius_and_diverts_fail_safe():
    m = monitor(max_airspeed_m_s=30.0)
    prelaunch(m)
    cmds = run(m, 0.0, 40.0, 90.0, valid=False)
    # the mean holds at the launch site; radius (30 + 0 + 0) (t - 0.1) + prediction 30 * 20:
    # 2000 - 50 - 30 (t - 0.1 + 20) <= 0 -> t = 45.1 s: not yet at 40 s
    assert cmds == []
    cmds = run(m, 40.0, 50.0, 90.0, valid=False)
    assert cmds and cmds[0][0] == pytest.approx(45.6, abs=ONE_UPDATE)
    assert any(e.kind == "geofence_heading_unknown" for e in m.drain_events())


def test_gnss_fix_then_dead_reckoning_from_the_last_fix():
    m = monitor()
    prelaunch(m)
    m.on_gnss_health(True)
    lat0, lon0 = math.radians(HOME[0]), math.radians(HOME[1])
    la, lo = vincenty_direct(lat0, lon0, math.radians(90.0), 1000.0)
    m.on_fc_position(5.0, math.degrees(la), math.degrees(lo), 550.0, 0.0, 20.0)
    m.step(sol(5.0, 90.0), air(5.0), 5.0)
    assert m.position_source == "gnss"
    assert m.state()["lon_deg"] == pytest.approx(math.degrees(lo), abs=1e-12)
    m.on_gnss_health(False)
    cmds = run(m, 5.0, 40.0, 90.0)
    assert m.position_source == "dead_reckoning"
    # from 1000 m east at t = 5: 2000 - 1000 - 20 (t - 5) - 50 <= 400 -> t = 32.5 s (+0.5 s)
    assert [c.name for _, c in cmds] == ["rtl"] and cmds[0][0] == pytest.approx(33.0, abs=ONE_UPDATE)
    kinds = [e.text for e in m.drain_events() if e.kind == "geofence_dr_start"]
    assert kinds == ["fence: position from FC GNSS", "fence: GNSS lost, DR from last fix"]


def test_corridor_polygon_contains_home_and_the_corridor_only():
    poly = np.radians(np.array(corridor_polygon(HOME[0], HOME[1], 60.0, 20.0, 8000.0, 300.0)))
    g = LocalGnomonic(math.radians(HOME[0]), math.radians(HOME[1]))
    xy = g.forward(poly[:, 0], poly[:, 1])
    lat0, lon0 = math.radians(HOME[0]), math.radians(HOME[1])

    def at(az, r):
        la, lo = vincenty_direct(lat0, lon0, math.radians(az), r)
        return g.forward(la, lo)
    pts = np.array([[0.0, 0.0], at(200.0, 250.0), at(60.0, 7900.0), at(45.0, 3000.0), at(75.0, 3000.0),
                    at(35.0, 3000.0), at(85.0, 3000.0), at(60.0, 8100.0), at(240.0, 400.0)])
    assert inside_polygon(pts, xy).tolist() == [True, True, True, True, True, False, False, False, False]


def test_corridor_config_diverts_when_leaving_the_sector():
    m = monitor(inclusion=[], corridor_azimuth_deg=0.0, corridor_half_width_deg=20.0, corridor_range_m=20000.0,
                corridor_home_radius_m=300.0, update_hz=5.0)
    prelaunch(m)
    assert run(m, 0.0, 60.0, 0.0, dt=0.2) == []       # along the corridor's centre: nothing
    cmds = run(m, 60.0, 200.0, 60.0, dt=0.2)          # turn 60 deg off the corridor
    assert [c.name for _, c in cmds] == ["rtl"]


def test_state_payload_units_and_schema():
    m = monitor()
    prelaunch(m)
    run(m, 0.0, 2.0, 90.0)
    st = m.state()
    assert st["schema"] == "azimuthd.geofence/1"
    for key in ("lat_deg", "lon_deg", "alt_m", "pos_sigma_major_m", "distance_to_fence_m", "clearance_m",
                "unknown_radius_m", "time_to_breach_s", "position_source", "latched", "armed"):
        assert key in st
    assert st["alt_m"] == pytest.approx(HOME[2] + 100.0)
    assert st["distance_to_fence_m"] == pytest.approx(2000.0 - 20.0 * 1.9, abs=0.01)


def test_events_payload_and_statustext_length():
    m = monitor()
    prelaunch(m)
    run(m, 0.0, 80.0, 90.0)
    evs = m.drain_events()
    assert all(len(e.text) <= 50 for e in evs)
    d = [e.to_dict() for e in evs if e.kind == "geofence_breach"][0]
    assert d["schema"] == "azimuthd.geofence/1" and d["severity"] == "critical"
    assert d["time_to_breach_s"] == pytest.approx(20.0) and d["source"] == "dead_reckoning"
    assert m.drain_events() == []


def test_height_reference_is_the_launcher_baro_else_isa():
    m = monitor()
    prelaunch(m)                       # pressure altitude 1000 m on the launcher
    run(m, 0.0, 1.0, 90.0, alt_rel=100.0)
    assert m.state()["alt_reference"] == "launch" and m.state()["alt_m"] == pytest.approx(HOME[2] + 100.0)
    m2 = monitor()                     # started in flight: no launcher sample
    run(m2, 0.0, 1.0, 90.0, alt_rel=100.0)
    assert m2.state()["alt_reference"] == "isa" and m2.state()["alt_m"] == pytest.approx(1100.0)


def test_a_late_daemon_predicts_from_the_age_of_its_input():
    # GIVEN 20 m/s due east from the launch site, 2000 m from the east edge (prompt: warning at
    # 77.6 s, test_predicted_breach_time_exact_without_uncertainty), and a daemon that reads its
    # input late: on time until 10 s, then falling behind by 0.5 s per FC second (its local
    # clock an arbitrary 1000 s ahead of the FC's)
    def lag_s(t):
        return max(0.0, 0.5 * (t - 10.0))

    def fly(lag):
        m = monitor()
        m.step(sol(0.0, 90.0, phase="pre-launch"), air(0.0, 0.0, 0.0), 1000.0)
        t, cmds = 0.0, []
        while t < 100.0 - 1e-9:
            t = round(t + 0.1, 6)
            cmds += [(t, c) for c in m.step(sol(t, 90.0), air(t), 1000.0 + t + lag(t))]
        return m, cmds
    m, cmds = fly(lag_s)
    ev = m.drain_events()
    # WHEN the monitor steps each solution at its late local time
    # THEN it predicts from the input's age a: warning when 2000 - 20 (t - 0.1 + a + 20) - 50 <= 0
    # with a = 0.5 (t - 10): t = 55.07 s FC time, i.e. local 77.6 s after the start, when a
    # prompt daemon warns; it says its input is late once a > 2 s (t = 14 s)
    warn = [e for e in ev if e.kind == "geofence_warning"]
    assert len(warn) == 1 and warn[0].time_fc_s == pytest.approx(55.07, abs=ONE_UPDATE)
    late = [e for e in ev if e.kind == "geofence_input_late"]
    assert len(late) == 1 and late[0].severity == "warning" and late[0].time_fc_s == pytest.approx(14.0, abs=ONE_UPDATE)
    assert [c.name for _, c in cmds] == ["rtl"] and cmds[0][0] == pytest.approx(55.57, abs=ONE_UPDATE)
    assert m.input_age_s == pytest.approx(lag_s(100.0), abs=1e-6)
    # and a constant clock offset is no lateness: the prompt figures, no late event
    m0, cmds0 = fly(lambda t: 0.0)
    ev0 = m0.drain_events()
    assert [e.time_fc_s for e in ev0 if e.kind == "geofence_warning"] == [pytest.approx(77.6, abs=ONE_UPDATE)]
    assert not any(e.kind == "geofence_input_late" for e in ev0) and m0.input_age_s == pytest.approx(0.0, abs=1e-6)
