"""Method B through a vertical launcher: its Euler output at |pitch| = 90 deg is reported, not refused.

B's attitude is Euler angles: T (euler_dot = T omega) is singular within 1e-6 rad of 90 deg pitch.
On a vertical launcher the FC says pitch 90 deg and B starts there; its output's covariance
T P T^T raised, so every B step was refused (the state never moved: B wedged for the whole flight,
each refusal counted as a rejected IMU sample) and Pipeline._start_flight raised halfway through
the take-off (bench/azimuth_accuracy.py --cases vertical --modes pipeline stopped at its second
flight; the daemon would have counted internal faults and rebuilt). Now the covariance is reported
with T at the margin's edge: roll and heading sigma huge (not separable there), pitch ordinary;
measurement Jacobians stay singular and say so."""
import dataclasses
import math

import numpy as np
import pytest

from estimators.ahrs_kf2 import Kf2Params, kf2_euler_and_cov, kf2_init
from estimators.euler_kinematics import euler_rate_matrix, euler_rate_matrix_reported
from estimators.rotations import quat_from_euler


@pytest.mark.parametrize("pitch_rad", [0.5 * math.pi, -0.5 * math.pi, 0.5 * math.pi - 3e-8])
def test_kf2_euler_cov_at_the_singularity(pitch_rad):
    s = kf2_init(quat_from_euler(0.3, pitch_rad, 1.0), Kf2Params())
    P = s.P.copy()
    P[0:3, 0:3] = np.eye(3) * math.radians(1.0) ** 2       # 1 deg about every body axis
    e, cov = kf2_euler_and_cov(dataclasses.replace(s, P=P))
    assert abs(abs(e[1]) - 0.5 * math.pi) < 1e-6
    assert np.all(np.isfinite(cov))
    assert math.sqrt(cov[1, 1]) == pytest.approx(math.radians(1.0))    # pitch: ordinary
    assert math.sqrt(cov[0, 0]) > 1e3 and math.sqrt(cov[2, 2]) > 1e3    # roll, heading: not separable
    with pytest.raises(ValueError, match="singular"):                   # a Jacobian still says so
        euler_rate_matrix(0.3, e[1])


def test_reported_matrix_is_continuous_outside_the_margin():
    """Outside the margin it is T itself; inside, T at twice the margin from 90 deg, sign kept."""
    assert np.array_equal(euler_rate_matrix_reported(0.2, 1.2), euler_rate_matrix(0.2, 1.2))
    assert np.array_equal(euler_rate_matrix_reported(0.2, 0.5 * math.pi),
                          euler_rate_matrix(0.2, 0.5 * math.pi - 2e-6))
    assert np.array_equal(euler_rate_matrix_reported(0.2, -0.5 * math.pi),
                          euler_rate_matrix(0.2, -0.5 * math.pi + 2e-6))


@pytest.mark.parametrize("backend", ["core", "python"])
@pytest.mark.parametrize("seed", [1, 5])
def test_vertical_launch_b_is_not_wedged(seed, backend, monkeypatch):
    """bench/azimuth_accuracy.py's vertical flights (seeds 1, 5: B started at the FC's pitch of
    90 deg), cut to 4 s after the launch: the take-off completes on both backends, no B step is
    refused as singular, and B's output after the launch is finite and moves with the vehicle."""
    from bench import azimuth_accuracy as aa
    from bench._truth_guard import sealed
    from bench.sitl import feed_pipeline, pipeline_inputs
    from service.pipeline import Pipeline
    from sim.offline import simulate

    rng = np.random.default_rng(10_000 * aa.CASES.index("vertical") + seed)
    scenario, ov = aa.flight_overrides("vertical", rng)
    run = simulate(scenario, seed=seed, imu_grade="consumer", imu_rate_hz=100.0, duration_s=aa.REST_S + 4.0,
                   overrides=ov)
    monkeypatch.setenv("AZIMUTHD_CORE", backend)
    p = Pipeline(aa.operator_config("vertical", ov, run.site, "full12", 100.0))
    if p.core.name != backend:
        pytest.skip(f"backend {backend} not available: {p.core.why}")
    pitches = []
    for sol in feed_pipeline(p, pipeline_inputs(sealed(run))):
        if p.phase.launch_time_s is not None and p.ahrs_out is not None and p.ahrs_out.valid:
            pitches.append(p.ahrs_out.pitch_rad)
    assert p.phase.launch_time_s is not None, "no take-off detected: the test does not reach the case"
    assert not [r for r in p.counters.reasons if "singular" in r], p.counters.reasons
    o = p.ahrs_out
    assert o is not None and o.valid and all(math.isfinite(v) for v in (o.roll_rad, o.pitch_rad, o.heading_rad,
                                                                        o.pitch_sigma_rad))
    assert len(pitches) > 50 and max(pitches) - min(pitches) > math.radians(1.0)   # B follows the climb-out
