"""Take-off detection per vehicle from the evidence a real vehicle gives (service/phases.py).

GIVEN synthetic IMU samples at 100 Hz (seeded noise) and the FC's evidence, WHEN the phases step
through them THEN the take-off is decided by the vehicle's own signature (boost, roll, lift-off,
the FC's landed state), and an impact, a taxi jolt or a push while disarmed is not a take-off.
"""
import math

import numpy as np
import pytest

from estimators.levelling import LevellingParams
from service.phases import IN_FLIGHT, LAUNCH, PRE_LAUNCH, FlightEvidence, PhaseParams, PhaseState, phase_step

G = 9.80665
DT = 0.01
REST = np.array([0.0, 0.0, -G])


def samples(t0, t1, accel=REST, rng=None, noise=0.02):
    rng = rng if rng is not None else np.random.default_rng(int(t0 * 100) + 1)
    return [(t, rng.normal(0, 1e-3, 3), np.asarray(accel, float) + rng.normal(0, noise, 3))
            for t in np.arange(t0, t1, DT)]


def run(seq, vehicle="launcher", evidence=None, state=None):
    params = PhaseParams(vehicle=vehicle, levelling=LevellingParams(min_samples=20))
    st, events = state or PhaseState(), []
    for t, g, a in seq:
        ev = evidence(t) if callable(evidence) else evidence
        st, e = phase_step(st, g, a, float(t), params, ev)
        events += [(float(t), *x) for x in e]
    return st, events


def kinds(events):
    return [k for _t, k, _d in events]


def test_an_impact_after_a_flight_is_not_a_second_take_off():
    """GIVEN a rail launch at 5 s, flight, then a landing impact of 155 m/s^2 WHEN the phases run
    THEN there is one take-off, at the boost."""
    impact = [(t, np.zeros(3), np.array([-150.0, 0.0, -40.0])) for t in np.arange(30.0, 30.1, DT)]
    st, ev = run(samples(0, 5) + samples(5, 5.4, [60.0, 0, -G]) + samples(5.4, 30) + impact + samples(30.1, 32))
    assert kinds(ev).count("takeoff") == 1 and abs(st.launch_time_s - 5.0) < 0.011 and st.phase == IN_FLIGHT


def test_an_impact_on_the_ground_is_refused_and_a_boost_still_launches():
    """GIVEN a vehicle levelled on the ground (a log whose flight was not recorded ends in a crash:
    |f| 155 m/s^2, backward and up) WHEN the spike comes THEN it is refused with its reason, and a
    later boost along the flight axis is the take-off."""
    crash = [(t, np.zeros(3), np.array([-150.0, 0.0, -45.0])) for t in np.arange(5.0, 5.1, DT)]
    st, ev = run(samples(0, 5) + crash + samples(5.1, 8))
    assert st.phase == PRE_LAUNCH and "takeoff" not in kinds(ev)
    refused = [d for _t, k, d in ev if k == "takeoff_refused"]
    assert len(refused) == 1 and "pointing backward" in refused[0] and "|f| = 157 m/s^2" in refused[0]
    st, ev = run(samples(8, 8.4, [60.0, 0, -G]) + samples(8.4, 9), state=st)
    assert "takeoff" in kinds(ev) and abs(st.launch_time_s - 8.0) < 0.011


def test_nothing_is_a_take_off_while_the_fc_says_disarmed():
    disarmed = FlightEvidence(armed=False)
    st, ev = run(samples(0, 5) + samples(5, 5.4, [60.0, 0, -G]) + samples(5.4, 6), evidence=disarmed)
    assert st.phase == PRE_LAUNCH and "takeoff" not in kinds(ev)
    assert [d for _t, k, d in ev if k == "takeoff_refused"][0].endswith("while the FC says disarmed: not a take-off")


def test_runway_roll_is_a_take_off_a_taxi_jolt_is_not():
    """GIVEN a runway vehicle levelled (pitched 2 deg on its wheels), a taxi jolt of 1.5 m/s^2 for
    0.5 s, then the roll at 2.5 m/s^2 from 10 s WHEN the phases run THEN the roll is the take-off
    (its start within the low-pass lag), the jolt is not; airborne when the baro climbs."""
    p = math.radians(2.0)
    rest = np.array([G * math.sin(p), 0.0, -G * math.cos(p)])
    fwd = np.array([math.cos(p), 0.0, math.sin(p)])  # the horizontal forward direction, sensor axes
    climb = lambda t: FlightEvidence(armed=True, alt_rate_m_s=3.0 if t > 16.0 else 0.0)  # noqa: E731
    seq = samples(0, 6, rest) + samples(6, 6.5, rest + 1.5 * fwd) + samples(6.5, 10, rest) \
        + samples(10, 18, rest + 2.5 * fwd)
    st, ev = run(seq, "runway", climb)
    assert kinds(ev).count("takeoff") == 1 and abs(st.launch_time_s - 10.0) < 0.15
    assert st.phase == IN_FLIGHT and any(k == "airborne" and "baro climb" in d for _t, k, d in ev)


def test_the_fc_landed_state_decides_a_gentle_lift_off():
    """GIVEN a multicopter that lifts off too gently for the IMU rule (0.3 m/s^2) WHEN its FC's land
    detector says "in the air" after "landed" THEN that is the take-off, at the FC's change."""
    fc = lambda t: FlightEvidence(armed=True, fc_landed=bool(t < 8.0))  # noqa: E731
    st, ev = run(samples(0, 8) + samples(8, 10, REST + [0, 0, -0.3]), "multicopter", fc)
    assert st.phase in (LAUNCH, IN_FLIGHT) and abs(st.launch_time_s - 8.0) < 0.011
    assert "landed state" in [d for _t, k, d in ev if k == "takeoff"][0]
    assert not st.started_in_flight


def test_the_fc_in_the_air_from_the_start_is_a_start_in_flight():
    """GIVEN the FC saying armed and in the air from the first sample (never landed) WHEN 1 s has
    passed THEN it is a start in flight, not a take-off."""
    st, ev = run(samples(0, 2), "multicopter", FlightEvidence(armed=True, fc_landed=False))
    assert st.started_in_flight and "takeoff" not in kinds(ev)
    assert "the FC reports in the air (landed state)" in st.in_flight_evidence


def test_a_multicopter_lift_off_from_the_imu():
    st, ev = run(samples(0, 6) + samples(6, 8, REST + [0, 0, -2.0]), "multicopter", FlightEvidence(armed=True))
    assert abs(st.launch_time_s - 6.0) < 0.15 and "vertical specific force" in st.launch_evidence


def test_vehicle_validated():
    with pytest.raises(ValueError, match="vehicle must be one of"):
        PhaseParams(vehicle="balloon")
