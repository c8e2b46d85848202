"""The IMU input checks in the compiled core equal their Python reference (issue 19 item 2).

GIVEN the IMU samples of a simulated flight (sim.offline inclined_rail, 100 Hz, 40 s) with every
kind of bad input injected in flight (NaN and inf, an axis at the int16 limit, an accelerometer
axis clipped at 16 g, a value beyond any IMU's range, a frozen driver that later recovers,
samples out of order, an FC clock that restarts 25 s lower, a 10 s gap), and the IMU samples of a
real log (/work/shared/data/px4-vtol-airspeed-small.ulg, through the log reader),
WHEN service/input_checks.py's ImuInputChecks (the reference) and CoreImuInputChecks (the
decisions in core/input_checks.hpp) check the same samples,
THEN every verdict is identical (the rejection reason, the events with their text, the reset
flag) and so are the counts per kind. Also: a deep copy of the core checks taken mid-fault goes on
as the unbroken run, and a Pipeline on the core backend uses the core checks.
"""
from __future__ import annotations

import copy
import functools
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import pipeline_inputs  # noqa: E402

from estimators import core  # noqa: E402
from mavlink_io.samples import ImuSample  # noqa: E402
from service.input_checks import (RAW_GYRO_LIMIT_RAD_S, CoreImuInputChecks, ImuInputChecks,  # noqa: E402
                                  InputCheckParams)
from sim.offline import simulate  # noqa: E402

DATA = Path("/work/shared/data")
pytestmark = pytest.mark.skipif(not core.CHECKS_AVAILABLE,
                                reason=f"compiled core without the input checks: {core.IMPORT_ERROR or 'old build'}")


def _with(s: ImuSample, **kw) -> ImuSample:
    f = dict(time_fc_s=s.time_fc_s, time_rx_s=s.time_rx_s, gyro_rad_s=s.gyro_rad_s, accel_m_s2=s.accel_m_s2,
             mag_gauss=s.mag_gauss, source=s.source)
    f.update(kw)
    return ImuSample(f["time_fc_s"], f["time_rx_s"], f["gyro_rad_s"], f["accel_m_s2"], f["mag_gauss"], f["source"])


@functools.lru_cache(maxsize=1)
def _faulted() -> tuple[ImuSample, ...]:
    run = simulate(scenario="inclined_rail", seed=5, imu_grade="consumer", imu_rate_hz=100.0, duration_s=40.0,
                   overrides={"launcher": {"rest_s": 8.0}})
    imu = [it for it in pipeline_inputs(run) if isinstance(it, ImuSample)]
    out = []
    frozen = None
    for k, s in enumerate(imu):
        t = s.time_fc_s
        if 12.0 <= t < 12.3:    # NaN / inf, alternating gyro and accel
            s = _with(s, gyro_rad_s=np.array([np.nan, 0.0, 0.0])) if k % 2 else \
                _with(s, accel_m_s2=np.array([0.0, np.inf, -9.8]))
        elif 13.0 <= t < 13.3:  # gyro x at RAW_IMU's int16 limit
            s = _with(s, gyro_rad_s=np.array([RAW_GYRO_LIMIT_RAD_S, *s.gyro_rad_s[1:]]))
        elif 14.0 <= t < 14.5:  # accel x clipped at 16 g (a run of bit-identical values)
            s = _with(s, accel_m_s2=np.array([16 * 9.80665, *s.accel_m_s2[1:]]))
        elif 15.0 <= t < 15.05:  # beyond any IMU's range
            s = _with(s, gyro_rad_s=np.array([0.0, 60.0, 0.0]))
        elif 16.0 <= t < 18.0:  # a driver resending one sample, then live again
            frozen = frozen or s
            s = _with(s, gyro_rad_s=frozen.gyro_rad_s.copy(), accel_m_s2=frozen.accel_m_s2.copy())
        elif 20.0 <= t < 35.0:  # the FC clock restarts 25 s lower (no reboot event)
            s = _with(s, time_fc_s=t - 25.0 if t < 27.0 else t - 5.0)
        out.append(s)
        if 18.5 <= t < 19.0 and k % 10 == 0:  # out of order: a sample 2 ms behind
            out.append(_with(s, time_fc_s=t - 0.002, gyro_rad_s=s.gyro_rad_s * 5))
    # a 10 s gap (after the restarted clock passed the old one), and one in receive time too
    return tuple([s for s in out if not 36.0 <= s.time_fc_s < 38.0] +
                 [_with(s, time_fc_s=s.time_fc_s + 10.0, time_rx_s=s.time_rx_s + 10.0) for s in imu[-5:]])


def _verdicts(checks, samples):
    return [(v.reject, v.events, v.reset) for v in map(checks.check, samples)]


def test_core_equals_reference_on_a_faulted_simulated_flight():
    samples = _faulted()
    params = InputCheckParams(report_interval_s=2.0)  # rate-limited reports with their counts show up too
    ref, cor = ImuInputChecks(params), CoreImuInputChecks(params)
    a, b = _verdicts(ref, samples), _verdicts(cor, samples)
    assert a == b
    assert ref.counts == cor.counts
    # every kind occurred (the comparison covers each branch) and events were said
    assert all(ref.counts[k] > 0 for k in ref.counts), ref.counts
    kinds = {e[1].split(":")[0] for v in a for e in v[1]}
    assert {"frozen_end", "time_reset_end"} <= kinds
    assert sum(1 for v in a if v[2]) == 1


def test_a_deep_copy_mid_fault_goes_on_as_the_unbroken_run():
    samples = _faulted()
    cut = next(k for k, s in enumerate(samples) if s.time_fc_s >= 16.8)  # inside the frozen run
    whole = CoreImuInputChecks()
    full = _verdicts(whole, samples)
    first = CoreImuInputChecks()
    head = _verdicts(first, samples[:cut])
    second = copy.deepcopy(first)
    tail = _verdicts(second, samples[cut:])
    assert head + tail == full
    assert second.counts == whole.counts and second.counts is not first.counts


@pytest.mark.skipif(not (DATA / "px4-vtol-airspeed-small.ulg").is_file(), reason="real logs not present")
def test_core_equals_reference_on_a_real_log():
    from service.logreaders import open_log
    samples = [it for it in open_log(DATA / "px4-vtol-airspeed-small.ulg").items() if isinstance(it, ImuSample)]
    assert len(samples) > 1000
    ref, cor = ImuInputChecks(), CoreImuInputChecks()
    assert _verdicts(ref, samples) == _verdicts(cor, samples)
    assert ref.counts == cor.counts


def test_the_pipeline_on_the_core_backend_uses_the_core_checks(monkeypatch):
    from service.config import validate
    from service.pipeline import Pipeline
    cfg = validate({"site": {"earth_field_ned_gauss": [0.2, 0.0, 0.4]}})
    monkeypatch.setenv("AZIMUTHD_CORE", "core")
    assert isinstance(Pipeline(cfg).input_checks, CoreImuInputChecks)
    monkeypatch.setenv("AZIMUTHD_CORE", "python")
    assert type(Pipeline(cfg).input_checks) is ImuInputChecks


def test_core_takes_list_valued_samples_as_the_reference():
    """An ImuSample whose gyro / accel are lists (a caller that is not the link): the core's checks read
    them as the reference does (they raised AttributeError on .tolist()), NaN included."""
    samples = [_with(s, gyro_rad_s=s.gyro_rad_s.tolist(), accel_m_s2=tuple(s.accel_m_s2.tolist()))
               for s in _faulted()[:1500]]
    assert any(not np.all(np.isfinite(s.gyro_rad_s)) or not np.all(np.isfinite(s.accel_m_s2)) for s in samples)
    params = InputCheckParams(report_interval_s=2.0)
    ref, cor = ImuInputChecks(params), CoreImuInputChecks(params)
    assert _verdicts(ref, samples) == _verdicts(cor, samples)
    assert ref.counts == cor.counts
