"""The incremental estimator end to end on analytical flights: each launch case, the gate, the API."""
from __future__ import annotations

import math

import numpy as np
import pytest

from estimators import azimuth as az
from estimators.azimuth_fit import GateParams
from estimators.levelling import LevellingParams
from estimators.launch_direction import LaunchDetectState, launch_detect_step
from estimators.rotations import dcm_from_quat, rot_x, rot_y, rot_z, wrap_pi
from test_azimuth_synth import E_NED_GAUSS, MANOEUVRE, launcher_attitude, make_flight

C_BS = rot_z(0.4) @ rot_y(-0.25) @ rot_x(0.9)   # a non-aligned IMU mount, C_body<-sensor


def run(fl, params, launch_time=None, mag_every=1):
    st = az.azimuth_init(params)
    tl = fl.launch_time_s if launch_time is None else launch_time
    outs = []
    launched = False
    for i, t in enumerate(fl.time_s):
        if not launched and t < tl:
            st = az.azimuth_prelaunch_step(st, fl.gyro_rad_s[i], fl.accel_m_s2[i], t)
            continue
        if not launched:
            st, why = az.azimuth_launch(st, fl.launch_time_s)
            assert why == ""
            launched = True
        mag = fl.mag_gauss[i] if i % mag_every == 0 else None
        st, out = az.azimuth_step(st, fl.gyro_rad_s[i], fl.accel_m_s2[i], mag, t)
        outs.append((i, out))
    return st, outs


def truth_azimuth(fl, i, v_sf):
    v = fl.C_nf_sf[i] @ v_sf
    return math.atan2(v[1], v[0]) % (2 * math.pi)


def params_for(case, model="seed7", C_bs=C_BS, **kw):
    return az.AzimuthParams(e_ned_gauss=E_NED_GAUSS, launch_case=case, distortion_model=model,
                            C_body_from_sensor=C_bs, **kw)


@pytest.mark.parametrize("case,model", [("vertical", "seed7"), ("inclined", "seed7"),
                                        ("aligned", "full12"), ("inclined", "none")])
def test_noiseless_flight_gives_exact_azimuth_for_each_launch_case(case, model):
    """GIVEN a noiseless analytical flight with gyro bias and injected distortion, WHEN the
    estimator runs through levelling, launch and flight, THEN every valid azimuth and heading
    equals the truth to < 1e-6 rad, and psi_s equals the launch yaw."""
    elev = math.pi / 2 if case == "vertical" else math.radians(55.0)
    C_nf_isf = launcher_attitude(math.radians(123.0), elev, C_BS, roll=0.3)
    if model == "none":
        A, b = np.eye(3), np.zeros(3)
    elif model == "seed7":
        A, b = np.diag([1.07, 0.94, 1.12]), np.array([0.08, -0.05, 0.03])
    else:
        A = np.array([[1.08, 0.05, -0.03], [0.02, 0.93, 0.06], [-0.04, 0.03, 1.04]])
        b = np.array([-0.06, 0.11, 0.02])
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE, A=A, b=b,
                     gyro_bias=np.array([0.01, -0.02, 0.015]))
    st, outs = run(fl, params_for(case, model))
    valid = [(i, o) for i, o in outs if o.valid]
    assert len(valid) > 100, outs[-1][1].reason
    for i, o in valid:
        assert abs(wrap_pi(o.azimuth_rad - truth_azimuth(fl, i, C_BS[0]))) < 1e-6
        assert abs(wrap_pi(o.heading_rad - truth_azimuth(fl, i, C_BS[0]))) < 1e-6
        np.testing.assert_allclose(dcm_from_quat(o.q_nav_from_body), fl.C_nf_sf[i] @ C_BS.T, atol=1e-6)
    last = valid[-1][1]
    assert abs(wrap_pi(last.psi_s_rad - fl.psi_s_rad)) < 1e-6
    if case != "vertical":  # a vertical nose has no azimuth at launch
        assert abs(wrap_pi(last.launch_azimuth_rad - math.radians(123.0))) < 1e-6
    np.testing.assert_allclose(last.distortion_A, A, atol=1e-6)
    np.testing.assert_allclose(last.distortion_b_gauss, b, atol=1e-6)
    # the flight direction found for the case equals the nose; the mount cross-check agrees
    np.testing.assert_allclose(last.u_sf, C_BS[0], atol=1e-9)
    if case != "aligned":
        assert last.cross_check_rad < 1e-6
    assert last.status == "solved" and last.reason == ""


def test_first_solution_waits_for_the_gate_and_names_the_reason():
    """Before the manoeuvre the field direction has not moved: the output is withheld with the
    diversity reason; once the sensor has turned, a solution appears."""
    C_nf_isf = launcher_attitude(1.0, 0.8, C_BS)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=[(np.array([0, 0, 0.0001]), 0.0, 6.0)] + MANOEUVRE,
                     A=np.diag([1.05, 0.95, 1.0]), b=np.array([0.05, 0.0, -0.02]), mag_noise_gauss=0.002)
    _, outs = run(fl, params_for("inclined", mag_noise_sigma_gauss=0.002))
    withheld = [o for _, o in outs if o.status == "withheld"]
    assert withheld, "never withheld"
    assert any(o.reason.startswith("orientation diversity") and "< 20 deg required" in o.reason for o in withheld)
    assert not any(o.valid for o in withheld)
    assert math.isnan(withheld[0].azimuth_rad)
    assert any(o.valid for _, o in outs)


def test_flight_without_rotation_never_gives_a_solution():
    C_nf_isf = launcher_attitude(2.0, 0.9, np.eye(3))
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=[1, 0, 0], segments=[], tail_s=15.0,
                     A=np.diag([1.05, 0.95, 1.0]), b=np.array([0.05, 0.0, -0.02]), mag_noise_gauss=0.002)
    _, outs = run(fl, params_for("aligned", C_bs=np.eye(3), mag_noise_sigma_gauss=0.002))
    last = outs[-1][1]
    assert not last.valid and last.status == "withheld"
    assert last.reason.startswith("orientation diversity 0.0 deg < 20 deg required")
    assert last.n_samples > 100


def test_noisy_flight_error_is_within_its_sigma():
    """Noise on all sensors: the azimuth error at the end stays within 4 sigma, sigma < 1 deg."""
    C_nf_isf = launcher_attitude(math.radians(300.0), math.radians(60.0), C_BS)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE, A=np.diag([1.05, 0.95, 1.1]),
                     b=np.array([0.05, -0.03, 0.02]), mag_noise_gauss=0.003, gyro_noise_rad_s=0.002,
                     accel_noise_m_s2=0.05, seed=4)
    _, outs = run(fl, params_for("inclined", levelling=LevellingParams(accel_bias_sigma_m_s2=0.01), gyro_scale_sigma=1e-4,
                                 gyro_misalign_sigma_rad=1e-4))
    i, o = outs[-1]
    err = wrap_pi(o.azimuth_rad - truth_azimuth(fl, i, C_BS[0]))
    assert o.valid
    assert 0.0 < o.azimuth_sigma_rad < math.radians(1.0)
    assert abs(err) < 4.0 * o.azimuth_sigma_rad, (math.degrees(err), math.degrees(o.azimuth_sigma_rad))


def test_late_launch_detection_replays_the_buffer():
    """A launch detected from the accelerometer (a few samples late) gives the same result as
    launching at the true instant: the delay line kept the first boost samples."""
    C_nf_isf = launcher_attitude(0.5, 0.9, C_BS)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE[:3], A=np.diag([1.05, 0.95, 1.0]))
    ld = LaunchDetectState()
    detected_at = None
    for i, t in enumerate(fl.time_s):
        ld = launch_detect_step(ld, fl.accel_m_s2[i], t)
        if ld.launch_time_s is not None:
            detected_at = t
            break
    assert detected_at is not None and detected_at > fl.launch_time_s
    assert abs(ld.launch_time_s - (fl.launch_time_s - 0.01)) < 1e-9   # last quiet sample
    p = params_for("inclined")
    st = az.azimuth_init(p)
    outs = []
    for i, t in enumerate(fl.time_s):
        if t <= detected_at:
            st = az.azimuth_prelaunch_step(st, fl.gyro_rad_s[i], fl.accel_m_s2[i], t)
            if t == detected_at:
                st, why = az.azimuth_launch(st, ld.launch_time_s)
                assert why == ""
            continue
        st, o = az.azimuth_step(st, fl.gyro_rad_s[i], fl.accel_m_s2[i], fl.mag_gauss[i], t)
        outs.append((i, o))
    i, o = outs[-1]
    assert o.valid
    assert abs(wrap_pi(o.azimuth_rad - truth_azimuth(fl, i, C_BS[0]))) < 1e-6


def test_levelling_failure_is_reported():
    C_nf_isf = launcher_attitude(0.5, 0.9, np.eye(3))
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=[1, 0, 0], rest_s=0.5, segments=MANOEUVRE[:1])
    st, outs = None, None
    p = params_for("aligned", C_bs=np.eye(3))
    st = az.azimuth_init(p)
    for i, t in enumerate(fl.time_s[:40]):
        st = az.azimuth_prelaunch_step(st, fl.gyro_rad_s[i], fl.accel_m_s2[i], t)
    st, why = az.azimuth_launch(st, fl.time_s[40])
    assert why.startswith("levelling failed:") and "still samples" in why
    st, o = az.azimuth_step(st, fl.gyro_rad_s[41], fl.accel_m_s2[41], fl.mag_gauss[41], fl.time_s[41])
    assert o.status == "failed" and not o.valid and o.reason == why


def test_class_wrapper_equals_pure_functions():
    C_nf_isf = launcher_attitude(0.5, 0.9, C_BS)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE[:3], mag_noise_gauss=0.002,
                     gyro_noise_rad_s=0.001, rest_s=2.5)
    p = params_for("inclined")
    _, outs = run(fl, p)
    est = az.AzimuthEstimator(p)
    k = 0
    for i, t in enumerate(fl.time_s):
        if t < fl.launch_time_s:
            est.prelaunch(fl.gyro_rad_s[i], fl.accel_m_s2[i], t)
            continue
        if k == 0:
            assert est.launch(fl.launch_time_s) == ""
        o = est.step(fl.gyro_rad_s[i], fl.accel_m_s2[i], fl.mag_gauss[i], t)
        ref = outs[k][1]
        k += 1
        assert o.status == ref.status
        if o.valid:
            assert o.azimuth_rad == ref.azimuth_rad and o.azimuth_sigma_rad == ref.azimuth_sigma_rad
    assert k == len(outs)


def test_params_are_validated():
    with pytest.raises(ValueError, match="launch_case"):
        params_for("sideways")
    with pytest.raises(ValueError, match="distortion_model"):
        params_for("inclined", model="seed8")
    with pytest.raises(ValueError, match="C_body_from_sensor"):
        params_for("inclined", C_bs=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="e_ned_gauss"):
        az.AzimuthParams(e_ned_gauss=np.array([0.0, 0.0, 0.5]))
    with pytest.raises(ValueError, match="min_samples"):
        GateParams(min_samples=0)
    with pytest.raises(ValueError, match="azimuth_step before azimuth_launch"):
        az.azimuth_step(az.azimuth_init(params_for("inclined")), np.zeros(3), np.zeros(3), None, 0.0)


def test_sigma_chain_predicts_the_effect_of_gyro_errors():
    """GIVEN a noiseless flight, WHEN the in-flight gyro gets a bias change db and a
    scale/misalignment matrix T, THEN the azimuth moves by (S_psi + k) . c as the consider
    analysis predicts (c = [-db, vec(T)]), to 2 % of the effect: this checks the estimator's G
    accumulation, the fit sensitivity S and the output sensitivity k together."""
    from estimators import azimuth_fit as af
    C_nf_isf = launcher_attitude(math.radians(200.0), math.radians(40.0), C_BS)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE, A=np.diag([1.05, 0.95, 1.1]),
                     b=np.array([0.05, -0.03, 0.02]))
    p = params_for("aligned", estimate_errors=False)
    st0, outs0 = run(fl, p)
    db = np.array([2e-4, -1e-4, 1.5e-4])
    T = np.array([[2e-3, -1e-3, 5e-4], [1e-3, -2e-3, 1e-3], [-5e-4, 1.5e-3, 1e-3]])
    flight = fl.time_s >= fl.launch_time_s
    fl2 = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE, A=np.diag([1.05, 0.95, 1.1]),
                      b=np.array([0.05, -0.03, 0.02]))
    fl2.gyro_rad_s[flight] = fl2.gyro_rad_s[flight] @ (np.eye(3) + T).T + db
    st1, outs1 = run(fl2, p)
    i, o0 = outs0[-1]
    o1 = outs1[-1][1]
    actual = wrap_pi(o1.azimuth_rad - o0.azimuth_rad)
    c = np.concatenate([-db, T.reshape(-1), [0.0, 0.0]])
    sol = st0.solution
    s0 = sol.fit.S_consider[0]
    Pc = np.outer(c, c)
    P_joint = np.block([[np.array([[s0 @ Pc @ s0]]), (s0 @ Pc)[None, :]], [(Pc @ s0)[:, None], Pc]])
    C_isf_sf = dcm_from_quat(st0.strapdown.q_ref_from_sensor)
    _, predicted_abs, _ = af.direction_azimuth_and_sigma(st0.u_sf, sol.C_nf_af, sol.C_af_isf, C_isf_sf,
                                                         st0.G_gyro, P_joint, 0.0)
    assert abs(actual) > math.radians(0.2)          # a sizeable effect ...
    assert abs(abs(actual) - predicted_abs) < 0.02 * abs(actual), (math.degrees(actual), math.degrees(predicted_abs))


def test_output_for_publishing_uses_degrees():
    C_nf_isf = launcher_attitude(math.radians(123.0), math.radians(55.0), C_BS)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE[:3])
    _, outs = run(fl, params_for("aligned"))
    i, o = outs[-1]
    d = az.output_for_publishing(o)
    assert d["valid"] and d["status"] == "solved"
    assert abs(d["launch_azimuth_deg"] - 123.0) < 1e-6
    assert abs(d["azimuth_deg"] - math.degrees(truth_azimuth(fl, i, C_BS[0]))) < 1e-6
    early = az.output_for_publishing(outs[0][1])
    assert not early["valid"] and math.isnan(early["azimuth_deg"])


def test_vertical_case_sigma_predicts_the_accelerometer_bias_effect():
    """GIVEN a vertical launch whose accelerometer has a bias (so the levelling and u = measured up
    are tilted together), WHEN the tilt is only considered, THEN the azimuth error equals the
    linear prediction (S_psi + k_tilt + k_u) . beta within 5 %: the u-tilt correlation term
    (du_dbeta) is needed for this."""
    from estimators import azimuth_fit as af
    C_nf_isf = launcher_attitude(math.radians(70.0), math.pi / 2, C_BS, roll=0.2)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE, A=np.diag([1.05, 0.95, 1.1]),
                     b=np.array([0.05, -0.03, 0.02]))
    fl.accel_m_s2 = fl.accel_m_s2 + np.array([0.15, -0.1, 0.05])
    st, outs = run(fl, params_for("vertical", estimate_errors=False))
    i, o = outs[-1]
    actual = wrap_pi(o.azimuth_rad - truth_azimuth(fl, i, C_BS[0]))
    # the tilt error beta (AF axes) of the levelling: C^_AF<-ISF = (I + [beta]x) C_AF<-ISF
    psi = fl.psi_s_rad
    C_af_isf_true = af.r3(psi) @ fl.C_nf_isf
    dC = st.C_isf_af.T @ C_af_isf_true.T
    beta = np.array([dC[2, 1], dC[0, 2], dC[1, 0]])
    c = np.concatenate([np.zeros(12), beta[:2]])
    sol = st.solution
    s0 = sol.fit.S_consider[0]
    Pc = np.outer(c, c)
    P_joint = np.block([[np.array([[s0 @ Pc @ s0]]), (s0 @ Pc)[None, :]], [(Pc @ s0)[:, None], Pc]])
    C_isf_sf = dcm_from_quat(st.strapdown.q_ref_from_sensor)
    _, pred, _ = af.direction_azimuth_and_sigma(st.u_sf, sol.C_nf_af, sol.C_af_isf, C_isf_sf, st.G_gyro,
                                                P_joint, 0.0, st.du_dbeta_sf)
    _, pred_without_u, _ = af.direction_azimuth_and_sigma(st.u_sf, sol.C_nf_af, sol.C_af_isf, C_isf_sf,
                                                          st.G_gyro, P_joint, 0.0)
    assert abs(actual) > math.radians(0.1)   # (beta_z is a yaw: psi_s absorbs it exactly)
    assert abs(abs(actual) - pred) < 0.05 * abs(actual), (math.degrees(actual), math.degrees(pred))
    assert abs(abs(actual) - pred_without_u) > 0.1 * abs(actual)


def test_solve_outside_the_step_equals_the_in_step_solve():
    """The daemon's worker path: with the in-step re-solve disabled, a solve on a snapshot merged
    into a later state gives that state the same solution, and keeps the samples that came after."""
    C_nf_isf = launcher_attitude(math.radians(123.0), math.radians(55.0), C_BS)
    fl = make_flight(C_nf_isf=C_nf_isf, u_sf=C_BS[0], segments=MANOEUVRE, A=np.diag([1.05, 0.95, 1.1]),
                     b=np.array([0.05, -0.03, 0.02]))
    p = params_for("aligned", resolve_period_s=math.inf, resolve_period_unsolved_s=math.inf)
    st, outs = run(fl, p)
    assert all(not o.valid for _, o in outs) and st.solution is None     # nothing solved in-step
    snap = az.azimuth_solve(st, float(fl.time_s[-2]))
    res = az.azimuth_solve_result(snap)
    later, _ = az.azimuth_step(st, fl.gyro_rad_s[-1], fl.accel_m_s2[-1], fl.mag_gauss[-1] * 1.0,
                               float(fl.time_s[-1]) + 0.2)
    merged = az.azimuth_apply_solve(later, res)
    assert merged.solution is not None and merged.solution.fit.psi_rad == snap.solution.fit.psi_rad
    assert len(merged.samples) == len(later.samples) == len(st.samples) + 1
    assert abs(wrap_pi(merged.solution.fit.psi_rad - fl.psi_s_rad)) < 1e-6
