"""The started-in-flight rule of service/phases.py (a daemon started or restarted in flight).

GIVEN synthetic IMU samples at 100 Hz and the evidence the daemon has (FC armed, airspeed, baro
altitude rate), WHEN the phases step through them THEN a vehicle armed and still on its launcher
levels and launches as before, and a vehicle that is flying goes straight to in-flight with a
``started_in_flight`` event naming the evidence, without levelling and without a launch.
"""
import math

import numpy as np
import pytest

from service.phases import (IN_FLIGHT, LAUNCH, PRE_LAUNCH, FlightEvidence, InFlightParams, PhaseParams,
                            PhaseState, phase_step)

G = 9.80665
DT = 0.01
RNG = np.random.default_rng(7)


def still(n, tilt_rad=0.0):
    """n samples at rest (pitched by tilt_rad), small noise."""
    f = np.array([G * math.sin(tilt_rad), 0.0, -G * math.cos(tilt_rad)])
    return [(RNG.normal(0, 0.002, 3), f + RNG.normal(0, 0.02, 3)) for _ in range(n)]


def run(samples, evidence, t0=100.0, state=None, params=PhaseParams()):
    st = state if state is not None else PhaseState()
    events, phases = [], []
    for k, (g, a) in enumerate(samples):
        t = t0 + k * DT
        ev = evidence(t) if callable(evidence) else evidence
        st, e = phase_step(st, g, a, t, params, ev)
        events += [(t, *x) for x in e]
        phases.append(st.phase)
    return st, events, phases


def kinds(events):
    return [e[1] for e in events]


def test_armed_and_still_on_the_launcher_levels_and_launches():
    armed = FlightEvidence(armed=True, airspeed_m_s=3.0, alt_rate_m_s=0.1)  # a breeze, baro noise
    st, ev, _ = run(still(600), armed)
    assert st.phase == PRE_LAUNCH and st.level is not None and not st.started_in_flight
    # while armed a passing block is held until decide_s: levelled at 4.5 s on the 2 s block
    t_level = next(t for t, k, _d in ev if k == "levelled")
    assert t_level == pytest.approx(100.0 + 4.5, abs=0.011)
    assert st.level.samples >= 200
    boost = [(np.zeros(3), np.array([40.0, 0.0, -G])) for _ in range(20)]
    st, ev2, _ = run(boost, armed, t0=106.0, state=st)
    assert st.phase == LAUNCH and st.launch_time_s == pytest.approx(106.0)
    assert "started_in_flight" not in kinds(ev + ev2)


def test_not_armed_levels_at_the_first_block_whatever_the_air_data():
    st, ev, _ = run(still(300), FlightEvidence(armed=None, airspeed_m_s=25.0, alt_rate_m_s=5.0))
    assert st.level is not None and st.phase == PRE_LAUNCH
    assert next(t for t, k, _d in ev if k == "levelled") == pytest.approx(102.0, abs=0.011)
    st, ev, _ = run(still(300), FlightEvidence(armed=False, airspeed_m_s=25.0))
    assert st.level is not None and "started_in_flight" not in kinds(ev)


def test_armed_with_airspeed_is_in_flight_after_the_hold():
    st, ev, phases = run(still(300), FlightEvidence(armed=True, airspeed_m_s=22.0))
    assert st.phase == IN_FLIGHT and st.started_in_flight and st.level is None and st.launch_time_s is None
    t_sif, _k, detail = next(e for e in ev if e[1] == "started_in_flight")
    assert t_sif == pytest.approx(101.0, abs=0.011)  # hold_s after the first sample
    assert "FC armed" in detail and "airspeed 22.0 m/s" in detail
    assert "levelled" not in kinds(ev) and LAUNCH not in phases


def test_a_gust_shorter_than_the_hold_is_no_evidence():
    def gusty(t):  # 0.5 s above the threshold every 2 s
        return FlightEvidence(armed=True, airspeed_m_s=15.0 if (t - 100.0) % 2.0 < 0.5 else 5.0)
    st, ev, _ = run(still(600), gusty)
    assert not st.started_in_flight and st.level is not None


def test_a_steady_climb_does_not_level():
    """The bench case: a steady climb passes the stillness test (specific force ~ gravity, quiet
    gyros); the baro altitude rate (settled after ~3 s) says it flies."""
    def climb(t):
        return FlightEvidence(armed=True, airspeed_m_s=None, alt_rate_m_s=5.0 if t >= 103.0 else None)
    st, ev, _ = run(still(600, tilt_rad=math.radians(12.0)), climb)
    assert st.started_in_flight and st.level is None
    detail = next(d for _t, k, d in ev if k == "started_in_flight")
    assert "baro altitude rate +5.0 m/s" in detail


def test_imu_not_still_for_long_enough_is_in_flight_but_a_short_handling_is_not():
    def shaky(n):
        return [(RNG.normal(0, 0.1, 3), np.array([0.0, 0.0, -G]) + RNG.normal(0, 1.0, 3)) for _ in range(n)]
    armed = FlightEvidence(armed=True)
    st, ev, _ = run(shaky(450), armed)  # two 2 s blocks failing back to back
    assert st.started_in_flight and "IMU not still for 4.0 s" in next(d for _t, k, d in ev if k == "started_in_flight")
    # handled for 2 s, then set down: levels
    st, ev, _ = run(shaky(200) + still(500), armed)
    assert not st.started_in_flight and st.level is not None


def test_sustained_specific_force_off_gravity_is_in_flight():
    turn = [(np.array([0.0, 0.0, 0.25]), np.array([0.0, 0.0, -G / math.cos(math.radians(40))]))
            for _ in range(150)]  # a 40 deg bank turn: |f| - g = 3.0 m/s^2
    st, ev, _ = run(turn, FlightEvidence(armed=True))
    assert st.started_in_flight and st.phase == IN_FLIGHT
    assert "| |f| - g | = 3.0 m/s^2" in next(d for _t, k, d in ev if k == "started_in_flight")
    st, ev, _ = run(turn, FlightEvidence(armed=None))
    assert not st.started_in_flight


def test_a_launch_right_after_the_start_is_a_launch():
    """Started 1 s before the launch (armed, no levelling yet, no evidence): a launch, as before."""
    armed = FlightEvidence(armed=True, airspeed_m_s=0.0, alt_rate_m_s=None)
    boost = [(np.zeros(3), np.array([40.0, 0.0, -G])) for _ in range(20)]
    st, ev, _ = run(still(100) + boost, armed)
    assert st.phase == LAUNCH and not st.started_in_flight
    assert "levelled" in kinds(ev)  # on the short rest


def test_in_flight_params_validated():
    with pytest.raises(ValueError, match="airspeed_m_s"):
        InFlightParams(airspeed_m_s=0.0)
    with pytest.raises(ValueError, match="decide_s"):
        InFlightParams(decide_s=math.nan)
