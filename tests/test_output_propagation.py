"""The attitude published between filter steps (estimators/output_propagation, Pipeline.propagated_solution)."""
import math

import numpy as np
import pytest

from estimators.output_propagation import output_reset, output_step
from estimators.rotations import quat_conj, quat_from_euler, quat_from_rotvec, quat_mul, rotvec_from_quat
from mavlink_io.samples import ImuSample
from service.config import validate
from service.pipeline import Pipeline

D = math.radians


def angle_between(q1, q2) -> float:
    return float(np.linalg.norm(rotvec_from_quat(quat_mul(q1, quat_conj(q2)))))


def test_a_rotation_about_a_fixed_axis_is_exact():
    # GIVEN an attitude and a 700 deg/s rotation about a fixed body axis, a gyro bias of 1 deg/s,
    # samples of the mean rate every 10 ms
    q0 = quat_from_euler(D(30.0), D(-50.0), D(200.0))
    axis = np.array([1.0, -2.0, 0.5]) / math.sqrt(5.25)
    bias = np.array([D(1.0), 0.0, D(-0.5)])
    st = output_reset(q0, 0.0)
    for k in range(1, 11):
        st = output_step(st, 0.01 * k, D(700.0) * axis + bias, bias, 0.5)
    # WHEN turned by 10 of them THEN the attitude is q0 q(700 deg/s x 0.1 s) to round-off (the coning
    # term of parallel increments is zero)
    q_true = quat_mul(q0, quat_from_rotvec(D(70.0) * axis))
    assert angle_between(np.array(st.q_nav_from_body), q_true) < 1e-12


def test_an_interval_it_cannot_integrate_ends_the_propagation():
    st = output_reset(quat_from_euler(0.0, 0.0, 0.0), 1.0)
    assert output_step(st, 1.0, np.zeros(3), np.zeros(3), 0.5) is None        # time not increasing
    assert output_step(st, 1.6, np.zeros(3), np.zeros(3), 0.5) is None        # a gap beyond max_dt_s
    assert output_step(st, 1.01, np.array([math.nan, 0, 0]), np.zeros(3), 0.5) is None


def _imu_stream(rate_hz=100.0, rest_s=4.0, spin_s=1.0, spin_deg_s=500.0):
    """(samples, true q_nav_from_body per sample): level, still, then a yaw spin; mean-rate samples."""
    dt = 1.0 / rate_hz
    g = 9.80665
    field = np.array([0.21, 0.01, 0.43])
    q = quat_from_euler(0.0, 0.0, D(40.0))
    out, truth = [], []
    for k in range(1, int(round((rest_s + spin_s) * rate_hz)) + 1):
        t = k * dt
        w = np.array([0.0, 0.0, D(spin_deg_s) if t > rest_s else 0.0])
        q = quat_mul(q, quat_from_rotvec(w * dt))
        C_bn = np.array(_dcm(q)).T
        out.append(ImuSample(t, t, w.copy(), C_bn @ np.array([0.0, 0.0, -g]), C_bn @ field, "RAW_IMU"))
        truth.append(q.copy())
    return out, truth


def _dcm(q):
    from estimators.rotations import dcm_from_quat
    return dcm_from_quat(q)


@pytest.fixture(scope="module")
def spin_run():
    cfg = validate({"site": {"lat_deg": 48.1, "lon_deg": 11.6, "alt_m": 500.0, "decimal_year": 2026.5},
                    "launch": {"case": "aligned", "vehicle": "hand"}, "heading": {"use_fc_yaw": False},
                    "azimuth": {"solve_in_background": False}, "mavlink": {"imu_rate_hz": 100.0}})
    p = Pipeline(cfg)
    samples, truth = _imu_stream()
    rows = []   # (t, filter step?, solution, true q)
    for s, q in zip(samples, truth):
        sol = p.on_imu(s)
        step = sol is not None
        prop = p.propagated_solution()
        if step and prop is not None:
            assert prop is sol          # right after a filter step: the step's own solution
        rows.append((s.time_fc_s, step, prop, q))
    return rows


def test_between_filter_steps_the_solution_follows_a_500_deg_s_spin(spin_run):
    # GIVEN a 100 Hz IMU (filter steps at 50 Hz) spinning at 500 deg/s after 4 s at rest
    between = [(sol, q) for t, step, sol, q in spin_run if not step and t > 4.05 and sol is not None]
    steps = [(sol, q) for t, step, sol, q in spin_run if step and t > 4.05]
    assert len(between) >= 45 and len(steps) >= 45
    # WHEN a sample between two filter steps comes THEN its solution is stamped with that sample and
    # its attitude is as close to the truth as the filter steps' (a solution held for one 10 ms sample
    # would be 5 deg behind)
    err_between = [angle_between(sol.q_nav_from_body, q) for sol, q in between]
    err_steps = [angle_between(sol.q_nav_from_body, q) for sol, q in steps]
    assert max(err_between) < max(err_steps) + D(0.2), (max(err_between), max(err_steps))
    assert max(err_between) < D(2.0)
    # AND its heading is the yaw of that attitude, its rates the newest sample's
    sol = between[-1][0]
    assert sol.heading_valid and sol.time_fc_s == pytest.approx(spin_run[-1][0] if not spin_run[-1][1]
                                                                else spin_run[-2][0])
    assert sol.rates_body_rad_s[2] == pytest.approx(D(500.0), rel=1e-2)


def test_nothing_is_propagated_before_the_attitude_filter_levelled():
    cfg = validate({"site": {"lat_deg": 48.1, "lon_deg": 11.6, "alt_m": 500.0, "decimal_year": 2026.5},
                    "launch": {"case": "aligned", "vehicle": "hand"}, "mavlink": {"imu_rate_hz": 100.0}})
    p = Pipeline(cfg)
    samples, _ = _imu_stream(rest_s=0.3, spin_s=0.0)
    for s in samples:
        p.on_imu(s)
        assert p.propagated_solution() is None
