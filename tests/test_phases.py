"""Phases: levelling blocks, launch detection, launch before a full still block."""
import math

import numpy as np

from service.phases import IN_FLIGHT, LAUNCH, PRE_LAUNCH, PhaseParams, phase_step, PhaseState

G = 9.80665
RNG = np.random.default_rng(5)


def run(samples, params=PhaseParams()):
    st, events = PhaseState(), []
    for t, gyro, accel in samples:
        st, ev = phase_step(st, gyro, accel, t, params)
        events += ev
    return st, events


def rest(t0, t1, dt=0.005, tilt_rad=0.1):
    f = np.array([0.0, -G * math.sin(tilt_rad), -G * math.cos(tilt_rad)])  # rolled by tilt_rad
    return [(t, RNG.normal(0, 1e-3, 3), f + RNG.normal(0, 0.02, 3)) for t in np.arange(t0, t1, dt)]


def boost(t0, t1, dt=0.005):
    return [(t, np.zeros(3), np.array([60.0, 0.0, -G])) for t in np.arange(t0, t1, dt)]


def cruise(t0, t1, dt=0.005):
    return [(t, np.zeros(3), np.array([0.0, 0.0, -G])) for t in np.arange(t0, t1, dt)]


def test_levels_then_detects_launch_then_flight():
    st, ev = run(rest(0, 5) + boost(5, 5.4) + cruise(5.4, 6))
    assert st.phase == IN_FLIGHT
    assert ("phase", PRE_LAUNCH) in ev and ("phase", LAUNCH) in ev and ("phase", IN_FLIGHT) in ev
    assert abs(st.launch_time_s - 5.0) < 0.006
    assert abs(st.level.roll_rad - 0.1) < 0.002 and abs(st.level.pitch_rad) < 0.002


def test_launch_before_a_full_still_block_levels_on_the_short_rest():
    # 1.0 s of rest < still_seconds (2 s): no block has passed when the boost comes
    st, ev = run(rest(0, 1.0) + boost(1.0, 1.4) + cruise(1.4, 2.0))
    assert st.phase == IN_FLIGHT and st.level is not None
    assert any(k == "levelled" and "short rest" in d for k, d in ev)
    assert abs(st.level.roll_rad - 0.1) < 0.005


def test_launch_with_no_rest_at_all_is_flagged_not_ignored():
    st, ev = run(boost(0.0, 0.4) + cruise(0.4, 1.0))
    assert st.phase == IN_FLIGHT and st.level is None
    assert any(k == "launch_unlevelled" for k, _ in ev)


def test_handling_on_the_launcher_is_not_a_launch_and_not_a_levelling():
    shaken = [(t, RNG.normal(0, 0.3, 3), np.array([0, 0, -G]) + RNG.normal(0, 1.5, 3))
              for t in np.arange(0, 2.5, 0.005)]
    st, ev = run(shaken)
    assert st.phase == PRE_LAUNCH and st.level is None
    assert any(k == "not_still" for k, _ in ev)
