"""Magnetometer usability (estimators/mag_usability.py): a sensor unfit for a heading is rejected with
a named reason; a good one, a slow-but-usable 2 Hz one and held repeats are not."""
import math
import re

import numpy as np
import pytest

from estimators.mag_usability import (MagUsabilityParams, MagUsabilityState, mag_usability_params_for_field,
                                      mag_usability_stale, mag_usability_step)

FIELD_NED_GAUSS = np.array([0.22, 0.01, 0.445])          # |B| 0.497 G, dip 63.7 deg
P = mag_usability_params_for_field(FIELD_NED_GAUSS)


def body_field(heading_rad, roll_rad=0.0, pitch_rad=0.0):
    """The model field in body axes for a ZYX attitude."""
    cy, sy = math.cos(heading_rad), math.sin(heading_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return (Rz @ Ry @ Rx).T @ FIELD_NED_GAUSS


def run(samples, rate_hz, duration_s, roll=0.1, pitch=-0.05, seed=1, noise_gauss=0.002, repeat_every=1,
        yaw_rate_rad_s=0.3):
    """Feed ``samples(t) -> body field`` with noise at ``rate_hz`` for ``duration_s``; each sample
    is also repeated ``repeat_every`` - 1 times (held onto the IMU samples in between); the gyros
    say the body yaws at ``yaw_rate_rad_s`` (the rate the samples' headings turn at)."""
    rng = np.random.default_rng(seed)
    st, verdicts = MagUsabilityState(), []
    dt = 1.0 / rate_hz
    w = np.array([0.0, 0.0, yaw_rate_rad_s])
    for k in range(int(duration_s * rate_hz)):
        t = k * dt
        m = samples(t) + rng.normal(0.0, noise_gauss, 3)
        for j in range(repeat_every):
            st, v = mag_usability_step(st, t + j * dt / repeat_every, m, roll, pitch, P, w)
            verdicts.append(v)
    return st, verdicts


def test_model_params():
    assert abs(P.field_norm_gauss - float(np.linalg.norm(FIELD_NED_GAUSS))) < 1e-12
    assert abs(math.degrees(P.field_dip_rad) - 63.7) < 0.1


def test_good_magnetometer_is_usable_after_one_window_and_reports_once():
    st, vs = run(lambda t: body_field(0.3 * t, 0.1, -0.05), 10.0, 10.0)
    assert all(not v.changed for v in vs if v.reason.startswith("being checked"))
    assert [v.usable for v in vs if v.changed] == [True]
    assert vs[-1].usable and vs[-1].reason == "" and abs(vs[-1].norm_ratio - 1.0) < 0.02
    assert abs(vs[-1].dip_rad - P.field_dip_rad) < math.radians(1.0)


def test_given_0p87_gauss_against_a_0p5_gauss_model_then_rejected_by_field_norm():
    st, vs = run(lambda t: body_field(0.3 * t, 0.1, -0.05) * (0.87 / P.field_norm_gauss), 10.0, 5.0)
    assert not vs[-1].usable
    m = re.match(r"field norm (\d\.\d{3}) G vs the model's 0\.497 G \(off by 7\d % > 25 %\)", vs[-1].reason)
    assert m and abs(float(m.group(1)) - 0.87) < 0.005, vs[-1].reason
    assert [v.usable for v in vs if v.changed] == [False]


def test_hard_iron_within_the_uncalibrated_prior_is_not_rejected():
    # 3 sigma of the uncalibrated hard iron (0.013 G per axis) on every axis: still the Earth's field
    bias = np.array([0.039, -0.039, 0.039])
    st, vs = run(lambda t: body_field(0.3 * t, 0.1, -0.05) + bias, 10.0, 10.0)
    assert vs[-1].usable, vs[-1].reason


def test_wrong_axis_mapping_is_rejected_by_dip():
    # z and x swapped (a mount/axis mistake): the norm is right, the dip is not
    st, vs = run(lambda t: body_field(0.3 * t, 0.1, -0.05)[[2, 1, 0]], 10.0, 5.0)
    assert not vs[-1].usable and vs[-1].reason.startswith("dip ")


def test_frozen_sensor_is_rejected_while_the_body_turns():
    m = body_field(1.0)
    st = MagUsabilityState()
    w = np.array([0.0, 0.0, 0.3])                      # yawing at 17 deg/s: a live sensor changes
    for k in range(50):
        st, v = mag_usability_step(st, 0.1 * k, m, 0.0, 0.0, P, w)
    assert not v.usable and v.reason.startswith("frozen: identical samples for 4.9 s while the gyros predict")


def test_given_a_noise_free_quantised_sensor_at_rest_then_it_is_not_called_frozen_or_slow():
    # ArduPilot's RAW_IMU (1 mG steps) from a quiet compass, or SITL's without SIM_MAG_RND: the
    # same reading for minutes while the vehicle sits still is no fault
    m = np.round(body_field(1.0) * 1000.0) / 1000.0
    rng = np.random.default_rng(4)
    st = MagUsabilityState()
    for k in range(600):                               # 60 s at 10 Hz, gyro noise only
        st, v = mag_usability_step(st, 0.1 * k, m, 0.0, 0.0, P, rng.normal(0.0, 0.002, 3))
    assert v.usable, v.reason
    # WHEN it then turns and the reading still does not change THEN frozen
    for k in range(600, 650):
        st, v = mag_usability_step(st, 0.1 * k, m, 0.0, 0.0, P, np.array([0.0, 0.0, 0.3]))
    assert not v.usable and v.reason.startswith("frozen")


def test_stuck_axis_is_reported_as_saturated():
    rng = np.random.default_rng(2)
    st = MagUsabilityState()
    for k in range(60):
        t = 0.1 * k
        m = body_field(0.3 * t) + rng.normal(0.0, 0.002, 3)
        m[2] = 0.8                                     # z clipped at the sensor's full scale
        # rolling (a yaw turn alone leaves m_z unchanged, so it cannot show a stuck z)
        st, v = mag_usability_step(st, t, m, 0.0, 0.0, P, np.array([0.3, 0.0, 0.3]))
    assert not v.usable and v.reason.startswith("saturated: axis z stuck at +0.800 G")


def test_full_scale_when_known():
    p = MagUsabilityParams(P.field_norm_gauss, P.field_dip_rad, full_scale_gauss=0.4)
    st, v = mag_usability_step(MagUsabilityState(), 0.0, np.array([0.41, 0.0, 0.2]), 0.0, 0.0, p)
    assert not v.usable and v.reason.startswith("saturated: |axis| 0.41 G >= full scale 0.40 G")


def test_two_hz_is_usable_half_hz_too_slow_and_held_repeats_do_not_count():
    # 2 Hz, each sample held onto 25 IMU-rate calls (50 Hz): usable, rate measured from changes only
    st, vs = run(lambda t: body_field(0.2 * t), 2.0, 12.0, repeat_every=25)
    assert vs[-1].usable and abs(vs[-1].rate_hz - 2.0) < 0.3
    st, vs = run(lambda t: body_field(0.2 * t), 0.5, 20.0, repeat_every=1)
    assert not vs[-1].usable and vs[-1].reason.startswith("too slow: 0.")


def test_no_samples_at_all_is_named():
    st, vs = run(lambda t: body_field(0.2 * t), 10.0, 3.0)
    st, v = mag_usability_stale(st, 4.0, P)
    assert v is None                                   # not yet frozen_s without a sample
    st, v = mag_usability_stale(st, 6.5, P)
    assert v is not None and not v.usable and v.changed and v.reason.startswith("no samples for 3.")
    st, v = mag_usability_stale(st, 7.0, P)
    assert v is None                                   # said once


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="mag_body_gauss must be 3 finite values"):
        mag_usability_step(MagUsabilityState(), 0.0, [0.1, float("nan"), 0.2], 0.0, 0.0, P)
    with pytest.raises(ValueError, match="norm_tolerance_fraction must be finite and > 0"):
        MagUsabilityParams(0.5, 1.0, norm_tolerance_fraction=0.0)
