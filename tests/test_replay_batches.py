"""``azimuthd replay`` hands the Pipeline batches of consecutive IMU samples (Pipeline.imu_batch_steps,
the compiled core's hot path behind it) and gives what the Python reference gives sample by sample.

GIVEN each real log in ../shared/data (skipped when absent) replayed as ``azimuthd replay`` runs it,
once with the compiled core (its hot path taking the quiet samples) and once with the reference
(``AZIMUTHD_CORE=python``: on_imu for every sample) THEN the rows, sigmas, sources, phases, events
(with their sample times) and the sample count agree (tests/parity_compare, 1e-9 relative); the
hot path took most of the samples between filter steps of a log that ends in flight (a log whose IMU
rate is at most the filter rate has none); and with the core, the batches give what the core's
on_imu gives sample by sample to 1e-9 (the simulated flight of tests/test_core_hot_path.py is compared
bit for bit)."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from parity_compare import differences  # noqa: E402
from pipeline_recording import fly, run_with_backend  # noqa: E402

from estimators import core as ec  # noqa: E402
from service import core_backend  # noqa: E402

pytestmark = pytest.mark.skipif(not ec.HOT_PATH_AVAILABLE, reason="compiled core without the hot path")
DATA = ROOT.parent / "shared" / "data"
LOGS = ("arducopter-flight.tlog", "arducopter-rtl-midflight.bin", "px4-bench-sample.ulg", "px4-quad-no-gnss.ulg",
        "px4-vtol-airspeed-small.ulg")
NO_SITE = ("px4-bench-sample.ulg", "px4-quad-no-gnss.ulg")


def _fly(name: str) -> dict:
    return fly(name, {}, {}, DATA, no_site=NO_SITE)


def _counting(backend):
    """The backend with its hot_run counting the rows it took."""
    took = [0]

    def run(*a):
        out = backend.hot_run(*a)
        took[0] += out[3]
        return out
    return dataclasses.replace(backend, hot_run=run), took


@pytest.mark.parametrize("name", LOGS)
def test_replay_in_batches_equals_the_reference(name):
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    counting, took = _counting(core)
    hot, p_hot = run_with_backend(_fly, name, counting)
    ref, _ = run_with_backend(_fly, name, core_backend.select({"AZIMUTHD_CORE": "python"}))
    each, _ = run_with_backend(_fly, name, dataclasses.replace(core, hot_run=None))
    assert hot["imu_samples"] == ref["imu_samples"] > 1000
    assert hot["events"] == ref["events"] == each["events"]
    bad = differences(ref, hot, name, 1e-9)
    assert not bad, bad[:5]
    bad = differences(each, hot, name, 1e-9)
    assert not bad, bad[:5]
    between = hot["imu_samples"] - len(hot["time_s"])   # the samples that are no filter step
    print(f"{name}: the hot path took {took[0]} of {hot['imu_samples']} samples ({between} between filter steps)")
    if p_hot.phase.phase == "in-flight" and between > 0:
        assert took[0] > 0.3 * between, (took[0], between)
