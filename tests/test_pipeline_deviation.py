"""Method D in the pipeline: learnt under a trusted heading, kept in an atomic state file."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import feed_pipeline, pipeline_inputs, scenario_site  # noqa: E402

from estimators.mag_deviation import DeviationState, deviation_coverage  # noqa: E402
from service import state_file  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sim.offline import simulate  # noqa: E402


@pytest.fixture(scope="module")
def calibrated():
    run = simulate("inclined_rail", seed=4, imu_rate_hz=100.0, duration_s=240.0)
    cfg = validate({**scenario_site("inclined_rail"), "deviation": {"calibrate": True}})
    p = Pipeline(cfg)
    events = []
    for _ in feed_pipeline(p, pipeline_inputs(run), events):
        pass
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
