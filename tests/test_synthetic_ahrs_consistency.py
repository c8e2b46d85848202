"""Method B's heading sigma must be honest: while aligned to the FC (a correlated reference) and
across an IMU gap (estimators/ahrs_kf2.kf2_unseen, estimators/synthetic_ahrs module docstring)."""
import math

import numpy as np
import pytest

from estimators.ahrs_kf2 import Kf2Params, kf2_consider_euler_cov, kf2_euler_and_cov, kf2_init, kf2_predict, kf2_unseen
from estimators.rotations import dcm_from_euler, quat_from_euler
from estimators.synthetic_ahrs import (FcAttitudeEvent, FcStatusEvent, ImuEvent, SyntheticAhrsParams, _consider_cov,
                                       synthetic_ahrs_init, synthetic_ahrs_step, synthetic_ahrs_unseen)

FIELD = np.array([0.23, 0.046, 0.394])
D = math.radians


def wrapd(a):
    return (a + 180.0) % 360.0 - 180.0


def test_kf2_gap_widens_attitude_like_method_c():
    p = Kf2Params()
    st = kf2_init(quat_from_euler(D(5.0), D(2.0), D(40.0)), p, sigma_tilt_rad=D(0.5), sigma_heading_rad=D(1.0))
    for k in range(101):
        st, _ = kf2_predict(st, np.zeros(3), 0.01 * k, p)
    sig0 = np.degrees(np.sqrt(np.diag(kf2_euler_and_cov(st)[1])))
    st, d = kf2_predict(st, np.zeros(3), 11.0, p)                  # 10 s gap
    assert not d.fused and d.reason.startswith("gap")
    sig = np.degrees(np.sqrt(np.diag(kf2_euler_and_cov(st)[1])))
    # min(20 deg/s x 9.9 s, 180 deg) heading, min(10 deg/s x 9.9 s, 30 deg) tilt, on top of before
    assert sig[2] == pytest.approx(math.hypot(sig0[2], 180.0), rel=0.02)
    assert sig[0] == pytest.approx(math.hypot(sig0[0], 30.0), rel=0.02)
    assert sig[1] == pytest.approx(math.hypot(sig0[1], 30.0), rel=0.02)
    # a short unseen interval widens by the rate: 0.5 s -> 10 deg heading, 5 deg tilt
    st1 = kf2_unseen(kf2_init(quat_from_euler(0.0, 0.0, 0.0), p, sigma_tilt_rad=D(0.1), sigma_heading_rad=D(0.1)),
                     0.5, p)
    s1 = np.degrees(np.sqrt(np.diag(kf2_euler_and_cov(st1)[1])))
    assert s1[2] == pytest.approx(math.hypot(0.1, 10.0), rel=0.01) and s1[0] == pytest.approx(math.hypot(0.1, 5.0), rel=0.01)
    with pytest.raises(ValueError):
        kf2_unseen(st1, -1.0, p)


def _flight(fc_yaw_error_deg, t_end_s, gap=None, yaw_turn_deg=0.0, signal_loss_s=None, seed=2):
    """Level, still vehicle at yaw 40 deg, 50 Hz IMU + magnetometer (true field, 0.002 G noise),
    the FC's ATTITUDE at 50 Hz with a constant yaw error (its correlated part). ``gap``: (t0, t1)
    with no event at all; the vehicle's yaw is ``yaw_turn_deg`` further after it."""
    rng = np.random.default_rng(seed)
    params = SyntheticAhrsParams(field_nav_gauss=tuple(FIELD))
    st = synthetic_ahrs_init(params)
    st, _ = synthetic_ahrs_step(st, FcStatusEvent(0.0, system_status=4, attitude_ok=True, horiz_pos_ok=True), params)
    outs = []
    for k in range(int(t_end_s * 50)):
        t = 0.02 * k
        if gap is not None and gap[0] <= t < gap[1]:
            continue
        yaw = D(40.0 + (yaw_turn_deg if gap is not None and t >= gap[1] else 0.0))
        if signal_loss_s is not None and abs(t - signal_loss_s) < 1e-9:
            st, _ = synthetic_ahrs_step(st, FcStatusEvent(t, horiz_pos_ok=False), params)
        fc = np.array([0.0, 0.0, yaw + D(fc_yaw_error_deg)]) + rng.normal(0.0, D(0.05), 3)
        st, _ = synthetic_ahrs_step(st, FcAttitudeEvent(t, fc), params, output=False)
        m = dcm_from_euler(0.0, 0.0, yaw).T @ FIELD + rng.normal(0.0, 0.002, 3)
        st, out = synthetic_ahrs_step(st, ImuEvent(t, rng.normal(0.0, D(0.02), 3), m), params)
        outs.append((t, wrapd(math.degrees(out.heading_rad - yaw)) if out.valid else math.nan,
                     math.degrees(out.heading_sigma_rad) if out.valid else math.nan, out.reference_trusted))
    return st, params, outs


def test_b2_aligned_to_the_fc_inherits_its_yaw_error_in_the_sigma():
    """The FC's yaw is 1 deg off for the whole minute (an FC heading error is correlated over tens
    of seconds). KF2 fuses it at 10 Hz as if white: its own heading variance collapses to ~0.2 deg
    while B's heading copies most of the FC's error. The published sigma must cover it."""
    st, params, outs = _flight(1.0, 60.0)
    t, err, sig, trusted = outs[-1]
    assert trusted and 0.3 < abs(err) < 1.2
    _, cov = kf2_euler_and_cov(st.kf2)
    assert math.degrees(math.sqrt(cov[2, 2])) < 0.4                   # the filter's own part
    assert 0.5 < st.ref_heading_sens <= 1.0
    assert abs(err) < 2.0 * sig                                         # the old sigma: 5 sigma
    # the magnetometer's consider share (its soft iron, the declination): next to nothing while the
    # FC's yaw is fused (its updates shrink the magnetometer's sensitivity as they shrink its error)
    consider = math.degrees(math.sqrt(kf2_consider_euler_cov(st.kf2, _consider_cov(st, params))[2, 2]))
    assert consider < 0.05
    assert sig == pytest.approx(math.sqrt(math.degrees(math.sqrt(cov[2, 2])) ** 2 + consider ** 2
                                          + (st.ref_heading_sens * math.degrees(params.fc_sigma_yaw_rad)) ** 2),
                                rel=1e-9)


def test_b2_after_a_gap_with_the_fc_trusted_is_realigned_to_it():
    """10 s without any input while the vehicle turned 90 deg: the gyro-only attitude of the
    agreement test did not see the turn, so the FC must not be judged as silently diverging (it
    would never be trusted again); B's sigma is wide at once and the FC takes it back."""
    st, params, outs = _flight(0.0, 22.0, gap=(10.0, 20.0), yaw_turn_deg=90.0)
    first = next(o for o in outs if o[0] >= 20.0)
    assert first[2] >= 29.9     # widened by the gap (180 deg), then re-taken from the magnetometer (30)
    assert not st.health.silent_divergence and outs[-1][3]              # trusted again
    late = [o for o in outs if o[0] >= 21.0]
    assert max(abs(o[1]) for o in late) < 1.0
    assert all(abs(o[1]) < 3.0 * o[2] for o in outs if o[0] > 0.0)


def test_b2_after_a_gap_without_the_fc_reacquires_the_heading_from_the_magnetometer():
    """GNSS lost (signalled) before a 10 s gap with a 90 deg turn: no reference after it. The
    linearised magnetometer update cannot pull 90 deg; the heading is re-taken from the levelled
    magnetometer, and every published sigma covers the error."""
    st, params, outs = _flight(0.0, 23.0, gap=(10.0, 20.0), yaw_turn_deg=90.0, signal_loss_s=5.0)
    assert not outs[-1][3]
    late = [o for o in outs if o[0] >= 20.5]
    assert max(abs(o[1]) for o in late) < 3.0     # tilt still wide (no air data here)
    assert all(abs(o[1]) < 3.0 * o[2] for o in outs if o[0] >= 5.0)
    assert st.kf2.n_resets >= 1 and not st.reacquire_heading


def test_b2_after_a_restarted_clock_runs_on_the_new_clock_with_a_wide_heading():
    """The FC rebooted: its clock starts again at 0 after 5 s not seen, during which the vehicle
    turned 90 deg; GNSS is gone (no reference). B must run on the new clock at once (it used to
    drop every sample until the new clock passed the old one) and re-take the heading."""
    st, params, outs = _flight(0.0, 12.0, signal_loss_s=5.0)
    with pytest.raises(ValueError):
        synthetic_ahrs_unseen(st, math.nan, params)
    st = synthetic_ahrs_unseen(st, 5.0, params)
    assert st.time_s is None and st.reacquire_heading
    rng = np.random.default_rng(5)
    yaw = D(130.0)
    st, _ = synthetic_ahrs_step(st, FcStatusEvent(0.0, system_status=4, attitude_ok=True, horiz_pos_ok=False), params)
    res = []
    for k in range(100):                                  # 2 s on the new clock
        t = 0.02 * k
        m = dcm_from_euler(0.0, 0.0, yaw).T @ FIELD + rng.normal(0.0, 0.002, 3)
        st, out = synthetic_ahrs_step(st, ImuEvent(t, rng.normal(0.0, D(0.02), 3), m), params)
        res.append((out.time_s, wrapd(math.degrees(out.heading_rad - yaw)), math.degrees(out.heading_sigma_rad)))
    assert res[-1][0] == pytest.approx(1.98)
    assert all(abs(e) < 3.0 * s for _t, e, s in res)
    assert abs(res[-1][1]) < 3.0 and not st.reacquire_heading
