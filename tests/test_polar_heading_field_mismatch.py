"""Method C's published heading sigma carries the field error the magnetometer itself shows against
the model (issue 18 item 3: a sigma below the error on a real log).

The real PX4 quadcopter log px4-quad-no-gnss.ulg (vehicle_magnetometer: the FC's calibrated field)
reads a dip of 75 deg where C takes its first heading and 66.5 deg in flight, against the model's
63.5 deg at the site: a field error of 0.08 and 0.023 G normal to the field in the magnetic
meridian, a component a levelled magnetometer can check. The component horizontal and normal to the
field turns the heading and cannot be checked. C published the prior of a calibrated airframe
(0.016 G hard iron, 1 deg soft iron: 6-8 deg) and 34 % of its rows were within 2 sigma of the FC.
Now the visible mismatch sets a per-axis error estimate that widens the consider term
(estimators/polar_heading.py, module docstring: field mismatch; the norm is left out, a scale error
turns no heading). Reference and compiled core alike.
"""
import math
from pathlib import Path

import numpy as np
import pytest

from estimators import core
from estimators import polar_heading as ref
from estimators.polar_heading import HeadingInputs, PolarHeadingParams, field_mismatch_var
from estimators.rotations import dcm_from_euler, quat_from_euler, wrap_pi

FIELD_NED_GAUSS = np.array([0.2153, 0.0138, 0.4334])   # WMM at 47.4 N 8.5 E: H 0.216 G, dip 63.5 deg
DECL_RAD = math.atan2(FIELD_NED_GAUSS[1], FIELD_NED_GAUSS[0])
QUAD_LOG = Path("/work/shared/data/px4-quad-no-gnss.ulg")

IMPLS = [pytest.param(ref, id="reference"),
         pytest.param(core, id="core", marks=pytest.mark.skipif(
             not core.POLAR_HEADING_AVAILABLE, reason="compiled core without C's heading filter"))]


def test_mismatch_is_the_visible_part_of_the_field_error():
    """GIVEN the model field seen level at heading 0.7 rad, WHEN a 0.02 G error is added along the
    field's normal in the magnetic meridian (a dip change), along the field itself (a scale error),
    or along the horizontal normal to the field, THEN the mismatch (per-axis variance) is 0.02^2 for
    the first and 0 for the other two: a scale error turns no heading, and the heading-turning
    component cannot be seen (only estimated from the first)."""
    psi = 0.7
    C_nb = dcm_from_euler(0.0, 0.0, psi)
    H0 = math.hypot(*FIELD_NED_GAUSS[:2])
    h_dir = np.array([FIELD_NED_GAUSS[0], FIELD_NED_GAUSS[1], 0.0]) / H0
    b_dir = FIELD_NED_GAUSS / np.linalg.norm(FIELD_NED_GAUSS)
    n_dir = (FIELD_NED_GAUSS[2] * h_dir - H0 * np.array([0.0, 0.0, 1.0])) / np.linalg.norm(FIELD_NED_GAUSS)
    p_dir = np.array([-h_dir[1], h_dir[0], 0.0])
    for d_ned, want, tol in ((0.02 * n_dir, 0.02 ** 2, 1e-6), (0.02 * b_dir, 0.0, 1e-15), (0.02 * p_dir, 0.0, 1e-6)):
        m_body = C_nb.T @ (FIELD_NED_GAUSS + d_ned)
        m_lev = C_nb @ m_body                                   # levelled (heading kept): NED
        H, Z = math.hypot(m_lev[0], m_lev[1]), m_lev[2]
        assert field_mismatch_var(H, Z, FIELD_NED_GAUSS) == pytest.approx(want, abs=tol)
    assert field_mismatch_var(0.2, 0.4, None) is None
    for bad in (np.array([0.2, math.nan, 0.4]), np.zeros(3), (0.2, 0.4)):
        with pytest.raises(ValueError, match="field_model_ned_gauss"):
            field_mismatch_var(0.2, 0.4, bad)


HOVER_PARAMS = PolarHeadingParams(gyro_bias_sigma_rad_s=math.radians(0.02))
"""A gyro bias known to 0.02 deg/s (a pre-launch rest and the zero-rate updates): the heading's own
P stays ~1 deg over the run, as C's converged P (~3 deg) in the real log, and the consider term is
what is tested."""


def _hover(impl, seed, hard_iron_sigma_gauss, with_model, platform=True, duration_s=30.0, imu_hz=20.0, mag_hz=2.0):
    """A multicopter hovering at a random heading and small tilt, exact gyros and tilt, a magnetometer
    at 2 Hz (PX4's default logging, as in the real log) with 0.002 G noise and a body-fixed field
    error drawn per axis N(0, hard_iron_sigma_gauss^2) (motor currents nobody compensated); the
    field itself is the model's. Returns (heading error rad, published sigma rad) at the end."""
    rng = np.random.default_rng(seed)
    psi = rng.uniform(0.0, 2.0 * math.pi)
    roll, pitch = rng.normal(0.0, math.radians(2.0), 2)
    hard_iron = rng.normal(0.0, hard_iron_sigma_gauss, 3)
    C_nb = dcm_from_euler(roll, pitch, psi)
    p = HOVER_PARAMS
    st = impl.polar_heading_init()
    n, every = int(duration_s * imu_hz), int(round(imu_hz / mag_hz))
    for k in range(n):
        t = k / imu_hz
        mag = C_nb.T @ FIELD_NED_GAUSS + hard_iron + rng.normal(0.0, 0.002, 3) if k % every == 0 else None
        u = HeadingInputs(t, np.zeros(3), roll, pitch, np.eye(2) * 1e-6, mag, DECL_RAD, 0.0063, None,
                          q_P_from_body=quat_from_euler(roll, pitch, 0.3) if platform else None,
                          cov_att_body_rad2=np.eye(3) * 1e-6 if platform else None,
                          field_model_ned_gauss=FIELD_NED_GAUSS if with_model else None)
        st, _ = impl.polar_heading_step(st, u, p)
    e = impl.polar_heading_estimate(st)
    return wrap_pi(e.heading_rad - psi), math.sqrt(e.variance_rad2)


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("platform", [False, True], ids=["euler", "platform"])
def test_uncompensated_motor_field_is_inside_the_published_sigma(impl, platform):
    """GIVEN 100 hovering multicopters, each with its own uncompensated body-fixed field error of
    0.04 G per axis (motor currents; the real quadcopter log shows 0.023 G in flight, 0.08 G where C
    starts), WHEN C publishes its heading with the model's field given, THEN the share of errors
    within 2 and 3 sigma is what a per-axis error estimated from one visible component allows (the
    hidden component over that estimate is Cauchy: 70 % and 80 %, more with the prior; measured
    here 70 % and 89 %) and the heading itself is unchanged; without the model (as before) the
    calibrated airframe's prior had 55 % and 78 %."""
    before, after = [], []
    for seed in range(100):
        before.append(_hover(impl, seed, 0.04, False, platform))
        after.append(_hover(impl, seed, 0.04, True, platform))
    rb = np.array([abs(e) / s for e, s in before])
    ra = np.array([abs(e) / s for e, s in after])
    eb, ea = np.array([e for e, _ in before]), np.array([e for e, _ in after])
    np.testing.assert_allclose(ea, eb, atol=1e-12)          # a consider term: the heading is the same
    assert np.mean(rb <= 2.0) <= 0.65 and np.mean(rb <= 3.0) <= 0.85, (np.mean(rb <= 2.0), np.mean(rb <= 3.0))
    assert np.mean(ra <= 2.0) >= 0.68 and np.mean(ra <= 3.0) >= 0.87, (np.mean(ra <= 2.0), np.mean(ra <= 3.0))
    # not wide for its own sake: the median error is about one sigma (0.67 for a Gaussian)
    assert 0.5 <= float(np.median(ra)) <= 1.5, float(np.median(ra))


@pytest.mark.parametrize("impl", IMPLS)
def test_a_field_on_the_model_keeps_the_calibrated_prior(impl):
    """GIVEN a clean magnetometer whose field is the model's, WHEN the model is given, THEN the
    published sigma is the one without it (the mismatch only widens; noise alone stays under the
    prior)."""
    e0, s0 = _hover(impl, 3, 0.0, False)
    e1, s1 = _hover(impl, 3, 0.0, True)
    assert e1 == e0 and s1 == s0


@pytest.mark.parametrize("impl", IMPLS)
def test_heading_initialised_from_a_distorted_field_is_wide(impl):
    """GIVEN a magnetometer on the ground beside steel, its field 0.42 G at a dip of 76 deg against
    the model's 0.484 G and 63.5 deg (the real quad log at its first usable sample reads ~75 deg),
    WHEN C takes its first heading from it, THEN the published sigma says how far off that field is
    (> 25 deg); the calibrated prior alone said ~10 deg."""
    H, Z = 0.42 * math.cos(math.radians(76.0)), 0.42 * math.sin(math.radians(76.0))
    field = np.array([H * math.cos(DECL_RAD), H * math.sin(DECL_RAD), Z])    # distorted, heading 0
    sig = {}
    for with_model in (False, True):
        st = impl.polar_heading_init()
        u = HeadingInputs(0.0, np.zeros(3), 0.0, 0.0, np.eye(2) * 1e-6, field, DECL_RAD, 0.0063, None,
                          q_P_from_body=quat_from_euler(0.0, 0.0, 0.0), cov_att_body_rad2=np.eye(3) * 1e-6,
                          field_model_ned_gauss=FIELD_NED_GAUSS if with_model else None)
        st, d = impl.polar_heading_step(st, u, PolarHeadingParams())
        assert d.reason == "initialised from source"
        sig[with_model] = math.degrees(math.sqrt(impl.polar_heading_estimate(st).variance_rad2))
    assert sig[False] < 12.0 and sig[True] > 25.0, sig


@pytest.mark.skipif(not QUAD_LOG.is_file(), reason="shared real logs not available")
def test_real_px4_quad_heading_within_its_sigma_of_the_fc():
    """GIVEN the real PX4 quadcopter log with no GNSS (its site assumed as an operator would give it,
    the FC's yaw excluded: our heading alone), WHEN it is replayed, THEN at least 90 % of the rows
    with a heading are within 2 published sigma of the FC's own heading (34 % before: a 6 deg sigma
    against a field 0.05 G off the model). The FC's heading is no truth here (it rests on the same
    magnetometer, and turns 21 deg in 3 s at 137.5 s while the log's gyros turn < 2 deg): it only
    scores."""
    from service.config import validate
    from service.logreaders import open_log
    from service.replay import run_replay
    cfg = validate({"site": {"lat_deg": 47.397, "lon_deg": 8.546},
                    "launch": {"vehicle": "multicopter", "case": "aligned"}})
    cfg["heading"]["use_fc_yaw"] = False
    res = run_replay(open_log(QUAD_LOG), cfg, None)
    h = np.array(res.cols["heading_deg"], float)
    s = np.array(res.cols["heading_sigma_deg"], float)
    r = np.array(res.cols["ref_heading_deg"], float)
    ok = np.isfinite(h) & np.isfinite(s) & np.isfinite(r)
    assert ok.sum() > 3000, ok.sum()
    err = (h[ok] - r[ok] + 180.0) % 360.0 - 180.0
    within = float(np.mean(np.abs(err) <= 2.0 * s[ok]))
    assert within >= 0.90, f"{within:.1%} within 2 sigma (median sigma {np.median(s[ok]):.1f} deg)"
