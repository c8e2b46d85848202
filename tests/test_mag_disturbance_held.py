"""A magnetometer sample held onto several IMU samples is one sample (issue 18 item 3; the false
hard-iron relearn on ArduPlane SITL's clean magnetometer).

RAW_IMU carries the compass's latest reading at the IMU rate and a log reader holds its MAG onto the
IMU samples, so the same vector comes again, later, with the attitude of a later IMU sample. Paired
with that attitude the reading is turned by rate x age: in ArduPlane SITL's 'ours' flight (a 10 Hz
MAG on a 100 Hz IMU, 84 % repeats) every banked turn's pair failed the NIS gate and the hard iron was
"re-learnt" three times (the heading then coasted on the gyros). estimators/mag_disturbance.py takes
a repeat for what it is: no new sample.

GIVEN a clean magnetometer (no hard or soft iron, no site distortion) read at 5 Hz and held onto a
100 Hz IMU, in the inclined rail's banked turns and climb flown with ArduPlane SITL's roll-in rate
(90 deg/s; the measured SITL maximum 92 deg/s), WHEN the daemon's Pipeline runs (the FC's yaw
excluded, as in the 'ours' flight) THEN the magnetometer is never rejected and its hard iron never
re-learnt (before: one relearn and a field-norm rejection in the same 60 s). Truth only scores.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_fc_yaw_excluded import fly  # noqa: E402

from estimators import core  # noqa: E402
from estimators import mag_disturbance as md  # noqa: E402
from estimators.rotations import quat_from_euler  # noqa: E402
from sim.offline import simulate  # noqa: E402

STEPS = [md.mag_disturbance_step] + ([core.mag_disturbance_step] if core.MAG_DISTURBANCE_AVAILABLE else [])


@pytest.mark.parametrize("step", STEPS, ids=lambda s: s.__module__)
def test_a_repeated_vector_is_no_new_sample(step):
    # GIVEN a sample taken at rest, then the body turned 40 deg in 0.5 s
    p = md.mag_disturbance_params_for_field(np.array([0.2, 0.0, 0.45]))
    m0 = np.array([0.2, 0.01, 0.45])
    st, v0 = step(md.MagDisturbanceState(), 0.0, m0, quat_from_euler(0.0, 0.0, 0.0), p)
    ref0 = st.to_state() if hasattr(st, "to_state") else st
    # WHEN the same vector comes again with the turned attitude (a held reading)
    st, v = step(st, 0.5, m0.copy(), quat_from_euler(0.0, 0.0, math.radians(40.0)), p)
    ref1 = st.to_state() if hasattr(st, "to_state") else st
    # THEN nothing was formed from it: no pair, the same state, the last fresh sample's verdict
    assert ref1.n_pairs == 0 and ref1.time_s == 0.0 and ref1.anchor[0] == 0.0
    assert np.array_equal(ref1.hard_iron_gauss, ref0.hard_iron_gauss) and ref1.norm_lp == ref0.norm_lp
    assert (v.usable, v.reason, v.changed, v.relearned) == (v0.usable, v0.reason, False, False)
    # ... and a new vector at the turned attitude pairs with the first one (dated 0.0)
    m1 = m0 + np.array([0.0, 0.0, 1e-4])
    st, _ = step(st, 0.6, m1, quat_from_euler(0.0, 0.0, math.radians(40.0)), p)
    ref2 = st.to_state() if hasattr(st, "to_state") else st
    assert ref2.n_pairs == 1 and ref2.time_s == 0.6
    # ... and the time test stays the reference's: a sample before the last new one is refused
    with pytest.raises(ValueError, match="must not decrease"):
        step(st, 0.55, m1 + 1e-4, quat_from_euler(0.0, 0.0, 0.0), p)


@pytest.fixture(scope="module")
def held_flight():
    clean = {"mag": {"hard_iron_gauss": [0.0, 0.0, 0.0], "soft_iron": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                     "site_distortion_ned_gauss": [0.0, 0.0, 0.0]},
             "launcher": {"rest_s": 5.0}, "flight": {"bank_rate_deg_s": 90.0}}
    start, length = 65.0, 60.0
    run = simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=100.0,
                   duration_s=start + length, overrides=clean)
    held = run.mag_gauss.copy()
    for k in range(len(held)):                     # a 5 Hz compass's latest reading on every IMU sample
        held[k] = run.mag_gauss[k - k % 20]
    run.mag_gauss = held
    import test_fc_yaw_excluded as fx
    old = fx.FEED_FROM_S, fx.FEED_S
    fx.FEED_FROM_S, fx.FEED_S = start, length        # its fly() feeds [FEED_FROM_S, + feed_s)
    try:
        p, sols, events = fly(run, {"use_fc_yaw": False}, feed_s=length)
    finally:
        fx.FEED_FROM_S, fx.FEED_S = old
    roll = np.degrees(run.truth.euler_rad[run.time_s >= start, 0])
    return p, sols, events, roll


def test_given_a_held_clean_magnetometer_in_banked_turns_then_no_disturbance_and_no_relearn(held_flight):
    p, sols, events, roll = held_flight
    assert np.max(np.abs(roll)) > 40.0                  # the banked turns were flown
    mag_events = [(k, d) for k, d in events if k in ("magnetic_disturbance", "magnetometer")]
    assert not any("hard iron changed" in d or d.startswith("rejected") for _k, d in mag_events), mag_events
    assert p.mag_dist.n_relearns == 0
    statuses = [status for sol, status in sols if sol.time_fc_s >= 70.0]   # after its first 5 s
    assert len(statuses) > 2500 and all(s == "usable" for s in statuses), set(statuses)
