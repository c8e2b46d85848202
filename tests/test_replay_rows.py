"""``azimuthd replay`` takes a reader's IMU samples as ImuBatch rows (``items(imu_batches=True)``:
the tlog reader passes on its link's batches, the ULog reader decodes the whole log into rows) and
gives exactly what it gives from the same reader's ImuSample objects.

GIVEN a simulated 400 Hz .tlog and a real ULog of ../shared/data (skipped when absent) WHEN each is
replayed once from the reader's batches and once from its samples (``items()``) THEN the Pipeline is
handed the same runs, and every row, sigma, source, phase, event (with its time) and count is the
same, bit for bit. AND a
reader whose batches are cut anywhere (rows 1, 700, 3, ... at a time, longer than the replay's
IMU_BATCH_MAX) gives the same as its samples one by one: the replay's runs are cut by the other items,
a change of source and IMU_BATCH_MAX, never by how a reader chunks its rows. AND the ULog reader's
samples are its batches' rows: the same times, values, magnetometer (None where a row has NaN) and
source."""
from __future__ import annotations

import itertools
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mavlink_io.imu_batch import ImuBatch  # noqa: E402
from mavlink_io.samples import ImuSample  # noqa: E402
from service.logreaders import open_log  # noqa: E402
from service.replay import IMU_BATCH_MAX, build_config, run_replay  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
VTOL = DATA / "px4-vtol-airspeed-small.ulg"
QUAD = DATA / "px4-quad-no-gnss.ulg"
SITE_FOR_NO_FIX = "47.37,8.54"


def _need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"{path} not present (the shared real logs)")
    return path


class _Reader:
    """A reader whose ``items`` are ``make(reader)``; everything else the reader's own."""

    def __init__(self, reader, make):
        self._r, self._make = reader, make

    def __getattr__(self, name):
        return getattr(self._r, name)

    def items(self, imu_batches: bool = False):
        return self._make(self._r)


def _replay(path: Path, make=None, site: str | None = None):
    """The ReplayResult, with ``runs``: the length of each batch handed to Pipeline.imu_batch_steps."""
    import service.pipeline as sp
    reader = open_log(path)
    cfg, _ = build_config(SimpleNamespace(config=None, site=site, exclude_fc_yaw=False), reader)
    runs = []
    steps = sp.Pipeline.imu_batch_steps

    def counted(self, batch, samples=None):
        runs.append(len(batch))
        return steps(self, batch, samples)
    mp = pytest.MonkeyPatch()
    mp.setattr(sp.Pipeline, "imu_batch_steps", counted)
    try:
        res = run_replay(reader if make is None else _Reader(reader, make), cfg, None)
    finally:
        mp.undo()
    res.runs = runs
    return res


def _same(a, b) -> None:
    assert a.imu_samples == b.imu_samples == sum(a.runs) > 1000
    assert a.runs == b.runs and max(a.runs) <= IMU_BATCH_MAX
    assert a.counts == b.counts
    assert a.events == b.events and a.phases == b.phases
    assert a.time_s == b.time_s and a.phase == b.phase and a.heading_source == b.heading_source
    for k in a.cols:
        assert np.array_equal(np.asarray(a.cols[k]), np.asarray(b.cols[k]), equal_nan=True), k
    for k in ("roll_sigma_deg", "pitch_sigma_deg"):
        assert np.array_equal(np.asarray(getattr(a, k)), np.asarray(getattr(b, k)), equal_nan=True), k


def _samples(reader):
    return reader.items()


@pytest.fixture(scope="module")
def sim_tlog(tmp_path_factory):
    """A simulated 10 s flight at 400 Hz as a ground station records it (bench/replay_speed.py): RAW_IMU
    as MAVLink 2, which the link decodes into ImuBatch rows (a v1 RAW_IMU goes through pymavlink)."""
    from bench.replay_speed import make_tlog_400hz
    path = tmp_path_factory.mktemp("sim") / "sim-400hz.tlog"
    site = make_tlog_400hz(path, 10.0)
    return path, f"{site['lat_deg']},{site['lon_deg']},{site['alt_m']}"


def test_tlog_batches_give_what_the_samples_give(sim_tlog):
    path, site = sim_tlog
    assert any(type(it) is ImuBatch for it in open_log(path).items(imu_batches=True))
    rows = _replay(path, site=site)
    assert "in-flight" in [p for p, _ in rows.phases]
    _same(rows, _replay(path, _samples, site))


def test_ulog_batches_give_what_the_samples_give():
    path = _need(VTOL)
    assert any(type(it) is ImuBatch for it in open_log(path).items(imu_batches=True))
    _same(_replay(path), _replay(path, _samples))


def _imu_only(items):
    """The IMU items alone: one run as long as the log, to be cut by IMU_BATCH_MAX."""
    return (it for it in items if type(it) in (ImuBatch, ImuSample))


def _rechunked(reader):
    """The reader's IMU rows, consecutive batches joined and cut again into 1, 700, 3, 250, ... rows."""
    sizes = itertools.cycle((1, 700, 3, 250, 2 * IMU_BATCH_MAX + 5))
    for batch in _imu_only(reader.items(imu_batches=True)):
        rec, i = batch.records, 0
        while i < len(rec):
            k = next(sizes)
            yield ImuBatch(rec[i:i + k], batch.source)
            i += k


def test_batches_cut_anywhere_give_what_the_samples_give():
    path = _need(QUAD)
    assert len(next(it for it in open_log(path).items(imu_batches=True) if type(it) is ImuBatch)) >= 1
    rows = _replay(path, _rechunked, SITE_FOR_NO_FIX)
    one_by_one = _replay(path, lambda r: _imu_only(r.items()), SITE_FOR_NO_FIX)
    assert rows.imu_samples > 4 * IMU_BATCH_MAX and rows.runs.count(IMU_BATCH_MAX) >= 4
    _same(rows, one_by_one)


def test_ulog_samples_are_its_rows():
    path = _need(VTOL)
    samples = [it for it in open_log(path).items() if type(it) is ImuSample]
    batches = [it for it in open_log(path).items(imu_batches=True) if type(it) is ImuBatch]
    rec = np.concatenate([b.records for b in batches])
    assert len(samples) == len(rec) > 1000
    assert {b.source for b in batches} == {s.source for s in samples} == {"sensor_combined"}
    for s, r in zip(samples, rec):
        assert s.time_fc_s == s.time_rx_s == r["time_fc_s"] == r["time_rx_s"]
        assert np.array_equal(s.gyro_rad_s, r["gyro_rad_s"]) and np.array_equal(s.accel_m_s2, r["accel_m_s2"])
        if s.mag_gauss is None:
            assert all(math.isnan(v) for v in r["mag_gauss"])
        else:
            assert np.array_equal(s.mag_gauss, r["mag_gauss"])
