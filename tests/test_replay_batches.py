"""``azimuthd replay`` hands the Pipeline batches of consecutive IMU samples (Pipeline.imu_batch_steps,
the compiled core's hot path behind it) and gives what the Python reference gives sample by sample.

GIVEN each real log in ../shared/data (skipped when absent) replayed as ``azimuthd replay`` runs it,
once with the compiled core (its hot path taking the quiet samples) and once with the reference
(``AZIMUTHD_CORE=python``: on_imu for every sample) THEN the rows, sigmas, sources, phases, events
(with their sample times) and the sample count agree (tests/parity_compare, 1e-9 relative); the
hot path took most of the samples between filter steps of a log that ends in flight (a log whose IMU
rate is at most the filter rate has none); and with the core, the batches give what the core's
on_imu gives sample by sample to 1e-9 (not bit for bit: the Pipeline itself is not reproducible to
the bit from run to run on some logs, see NOT_REPRODUCIBLE; the simulated flight of
tests/test_core_hot_path.py is, and is compared bit for bit)."""
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


NOT_REPRODUCIBLE = {"px4-quad-no-gnss.ulg": 1e-7}
"""Logs whose heading column the Pipeline does not reproduce to 1e-9 relative from run to run,
whatever the backend and the batching (measured 2026-12-02, the core with on_imu per sample, the
same PYTHONHASHSEED): on px4-quad-no-gnss.ulg from C's magnetometer heading acquisition at 124.4 s on,
the first replays in two processes differ by 1.0e-10 relative, a second replay in the same process
by 1.1e-8 from the first (state carried from one Pipeline to the next in a process: not found yet).
The runs below are in one process, so that column is compared to this tolerance there."""


def _differences(a: dict, b: dict, name: str, rtol: float) -> list:
    tol = NOT_REPRODUCIBLE.get(name)
    if tol is None:
        return differences(a, b, name, rtol)
    bad = differences(a["cols"]["heading_deg"], b["cols"]["heading_deg"], name + ".cols.heading_deg", max(rtol, tol))
    strip = lambda r: {**r, "cols": {k: v for k, v in r["cols"].items() if k != "heading_deg"}}  # noqa: E731
    return bad + differences(strip(a), strip(b), name, rtol)


@pytest.mark.parametrize("name", LOGS)
def test_replay_in_batches_equals_the_reference(name):
    core = core_backend.select({"AZIMUTHD_CORE": "core"})
    counting, took = _counting(core)
    hot, p_hot = run_with_backend(_fly, name, counting)
    ref, _ = run_with_backend(_fly, name, core_backend.select({"AZIMUTHD_CORE": "python"}))
    each, _ = run_with_backend(_fly, name, dataclasses.replace(core, hot_run=None))
    assert hot["imu_samples"] == ref["imu_samples"] > 1000
    assert hot["events"] == ref["events"] == each["events"]
    bad = _differences(ref, hot, name, 1e-9)
    assert not bad, bad[:5]
    bad = _differences(each, hot, name, 1e-9)
    assert not bad, bad[:5]
    between = hot["imu_samples"] - len(hot["time_s"])   # the samples that are no filter step
    print(f"{name}: the hot path took {took[0]} of {hot['imu_samples']} samples ({between} between filter steps)")
    if p_hot.phase.phase == "in-flight" and between > 0:
        assert took[0] > 0.3 * between, (took[0], between)
