"""Method D in the pipeline: learnt under a trusted heading, kept in an atomic state file."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import scenario_site  # noqa: E402

from estimators.mag_deviation import DeviationState, deviation_coverage  # noqa: E402
from mavlink_io.samples import FcAttitude, ImuSample, PressureSample  # noqa: E402
from service import state_file  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sim.offline import simulate  # noqa: E402


@pytest.fixture(scope="module")
def calibrated():
    run = simulate("inclined_rail", seed=4, imu_rate_hz=100.0, duration_s=240.0)
    cfg = validate({**scenario_site("inclined_rail"), "deviation": {"calibrate": True}})
    p = Pipeline(cfg)
    kb = kf = 0
    events = []
    for k, t in enumerate(run.time_s):
        while kb < len(run.baro_time_s) and run.baro_time_s[kb] <= t:
            p.on_pressure(PressureSample(run.baro_time_s[kb], 0.0, run.press_abs_pa[kb], run.press_diff_pa[kb],
                                         run.temperature_k[kb]))
            kb += 1
        while kf < len(run.fc_time_s) and run.fc_time_s[kf] <= t:
            e = run.fc_euler_rad[kf]
            p.on_fc_attitude(FcAttitude(run.fc_time_s[kf], 0.0, e[0], e[1], e[2], np.zeros(3)))
            kf += 1
        p.on_imu(ImuSample(t, 0.0, run.gyro_rad_s[k], run.accel_m_s2[k], run.mag_gauss[k], "RAW_IMU"))
        events += p.drain_events()
    return p, events


def test_learns_only_against_a_trusted_heading_and_reports_coverage(calibrated):
    p, events = calibrated
    dev = p.deviation
    assert dev is not None and dev.n > 500          # 10 Hz while the FC (or A) gave the heading
    cov = deviation_coverage(dev, p.deviation_params)
    assert cov.heading_fraction > 0.5                        # the turns and the figure-eight swept headings
    assert any(k == "deviation" and "coverage" in d for k, d in events)
    assert np.all(np.isfinite(dev.coeffs))


def test_state_file_round_trip_and_corrupt_file_set_aside(calibrated, tmp_path):
    p, _ = calibrated
    path = tmp_path / "deviation.json"
    assert state_file.write_document(path, "azimuthd-magnetometer-deviation", 1, {"state": p.deviation.to_dict()}) == ""
    payload, status = state_file.read_document(path, "azimuthd-magnetometer-deviation", 1)
    assert status == "loaded"
    back = DeviationState.from_dict(payload["state"])
    np.testing.assert_array_equal(back.coeffs, p.deviation.coeffs)
    np.testing.assert_array_equal(back.P, p.deviation.P)
    path.write_bytes(path.read_bytes()[:-40])        # truncated by a crash of something else
    payload, status = state_file.read_document(path, "azimuthd-magnetometer-deviation", 1)
    assert payload is None and status.startswith("corrupt") and (tmp_path / "deviation.json.corrupt").exists()
    assert not path.exists()
