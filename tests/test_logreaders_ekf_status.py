"""The FC's estimator status from logs (issue 18: the FC is no reference before its estimator says so).

9054df3 made the FC's attitude no reference until its first estimator status. DataFlash and ULog
replays carried none, so every replay waited ``status_wait_s`` (5 s) with the FC untrusted: on
arducopter-rtl-midflight.bin (started in flight) the heading went 0.45 -> 2.39 deg RMS with the FC
allowed and 1.82 -> 6.45 with it excluded. Now the readers give the status the log records (XKF4/NKF4
SS; estimator_status.solution_status_flags) and a log that records none is judged without one from
its first ATTITUDE (service/replay.py -> Pipeline.fc_sends_no_status)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mavlink_io.samples import FcAttitude, FcEkfStatus, ImuSample
from service.logreaders import open_log
from service.pipeline import Pipeline
from tests.test_logreaders_formats import (PITCH_DEG, ROLL_DEG, DataflashWriter, px4_ulog,
                                           specific_force)

SS_ATTITUDE, SS_HORIZ_POS_ABS = 1, 16


def dataflash_with_ekf(path, *, ekf="XKF4", cores=(0, 1), ss_core0=SS_ATTITUDE | SS_HORIZ_POS_ABS,
                       ss_core1=0, ahrs_ekf_type=3, seconds=2.0):
    """IMU at 100 Hz, ATT and the EKF status (per core) at 10 Hz, AHRS_EKF_TYPE as a PARM."""
    w = DataflashWriter()
    w.fmt(129, "IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    w.fmt(130, "ATT", "Qccc", "TimeUS,Roll,Pitch,Yaw")
    w.fmt(131, "PARM", "QNf", "TimeUS,Name,Value")
    if ekf == "XKF4":
        w.fmt(132, "XKF4", "QBffffI", "TimeUS,C,SV,SP,SH,SM,SS")
    else:  # EKF2's NKF4: no core column (core 0)
        w.fmt(132, "NKF4", "QffffI", "TimeUS,SV,SP,SH,SM,SS")
    if ahrs_ekf_type is not None:
        w.rec("PARM", 4_000_000, b"AHRS_EKF_TYPE".ljust(16, b"\0"), float(ahrs_ekf_type))
    f = specific_force(ROLL_DEG, PITCH_DEG)
    for k in range(int(100 * seconds)):
        t = 5_000_000 + 10_000 * k
        w.rec("IMU", t, 0, 0.0, 0.0, 0.0, *f)
        if k % 10 == 0:
            w.rec("ATT", t + 5, int(ROLL_DEG * 100), int(PITCH_DEG * 100), 0)
            if ekf == "XKF4":
                for c in cores:
                    w.rec("XKF4", t + 6, c, 0.1, 0.2, 0.3, 0.4, ss_core0 if c == 0 else ss_core1)
            else:
                w.rec("NKF4", t + 6, 0.1, 0.2, 0.3, 0.4, ss_core0)
    path.write_bytes(w.bytes())


def test_dataflash_xkf4_gives_the_first_cores_status_with_its_test_ratios(tmp_path):
    p = tmp_path / "ekf3.bin"
    dataflash_with_ekf(p)
    r = open_log(p)
    assert r.estimator_status == "XKF4"
    st = [i for i in r.items() if type(i) is FcEkfStatus]
    assert len(st) == 20                        # core 0 only, 10 Hz for 2 s
    assert all(s.attitude_ok and s.horiz_pos_ok and s.source == "XKF4" for s in st)
    assert st[0].time_fc_s == pytest.approx(5.000006)
    assert (st[0].velocity_variance, st[0].compass_variance) == (pytest.approx(0.1), pytest.approx(0.4))


def test_dataflash_status_bits_say_attitude_and_position_apart(tmp_path):
    p = tmp_path / "ekf3_nopos.bin"
    dataflash_with_ekf(p, ss_core0=SS_ATTITUDE)
    st = [i for i in open_log(p).items() if type(i) is FcEkfStatus]
    assert st and all(s.attitude_ok and not s.horiz_pos_ok for s in st)
    p2 = tmp_path / "ekf3_uninit.bin"
    dataflash_with_ekf(p2, ss_core0=0)
    st2 = [i for i in open_log(p2).items() if type(i) is FcEkfStatus]
    assert st2 and not any(s.attitude_ok for s in st2)


def test_dataflash_ekf2_nkf4_and_a_log_without_status(tmp_path):
    p = tmp_path / "ekf2.bin"
    dataflash_with_ekf(p, ekf="NKF4", ahrs_ekf_type=2)
    r = open_log(p)
    assert r.estimator_status == "NKF4"
    assert sum(type(i) is FcEkfStatus for i in r.items()) == 20
    # AHRS_EKF_TYPE 3 but only EKF2's record logged: not the EKF the AHRS used -> none, said
    p3 = tmp_path / "mismatch.bin"
    dataflash_with_ekf(p3, ekf="NKF4", ahrs_ekf_type=3)
    r3 = open_log(p3)
    assert r3.estimator_status is None
    assert not any(type(i) is FcEkfStatus for i in r3.items())
    assert any("no EKF solution status" in n for n in r3.summary.notes)


def test_ulog_status_flags_and_a_px4_that_left_them_zero(tmp_path):
    p = tmp_path / "status.ulg"
    px4_ulog(p, status_flags=SS_ATTITUDE | 4 | 32)   # attitude, vertical velocity/position: no GNSS position
    r = open_log(p)
    assert r.estimator_status == "estimator_status"
    st = [i for i in r.items() if type(i) is FcEkfStatus]
    assert len(st) == 20 and all(s.attitude_ok and not s.horiz_pos_ok for s in st)
    assert st[0].compass_variance == pytest.approx(0.25) and math.isnan(st[0].velocity_variance)
    p0 = tmp_path / "status0.ulg"
    px4_ulog(p0, status_flags=0)                    # an old PX4 that never filled the flags: no status at all
    r0 = open_log(p0)
    assert r0.estimator_status is None
    assert not any(type(i) is FcEkfStatus for i in r0.items())
    assert sum("0 throughout" in n for n in r0.summary.notes) == 1


RATE_HZ = 50.0


@pytest.fixture(scope="module")
def run():
    from sim.offline import simulate
    return simulate(scenario="runway_takeoff", seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ, duration_s=7.0)


def _trusted_from_s(run, told: bool, monkeypatch, core: str, status_first: bool = False) -> float:
    """First FC time at which B trusts a good FC that sends no estimator status (its ATTITUDE the
    simulator's FC attitude from t = 0), with the Pipeline told so (a log recording none) or not."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from sitl import feed_pipeline, scenario_site
    from mavlink_io.samples import PressureSample
    from service.config import validate
    monkeypatch.setenv("AZIMUTHD_CORE", core)
    site = scenario_site("runway_takeoff")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    p = Pipeline(validate({**site, "mavlink": {"imu_rate_hz": RATE_HZ}}))
    if told:
        p.fc_sends_no_status("the log records no FC estimator status")
    items = [(t, 2, ImuSample(t, t, g.copy(), a.copy(), m.copy(), "RAW_IMU", 0))
             for t, g, a, m in zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss)]
    items += [(t, 1, PressureSample(t, t, pa, d, k)) for t, pa, d, k in
              zip(run.baro_time_s.tolist(), run.press_abs_pa.tolist(), run.press_diff_pa.tolist(),
                  run.temperature_k.tolist())]
    items += [(t, 0, FcAttitude(t, t, *(float(v) for v in e), np.zeros(3)))
              for t, e in zip(run.fc_time_s.tolist(), run.fc_euler_rad)]
    items.sort(key=lambda x: (x[0], x[1]))
    if status_first:   # one good status before anything else (an FC already running when we connect), none after
        items.insert(0, (0.0, -1, FcEkfStatus(0.0, True, True, 831, "EKF_STATUS_REPORT")))
    events: list = []
    for sol in feed_pipeline(p, [it for _t, _o, it in items], events, timed_events=True):
        if p.ahrs_out is not None and p.ahrs_out.reference_trusted:
            return sol.time_fc_s
    return math.inf


@pytest.mark.parametrize("core", ["core", "python"])
def test_a_log_without_status_is_judged_without_one_from_its_first_attitude(run, core, monkeypatch):
    """GIVEN a good FC whose log records no estimator status WHEN replayed THEN B trusts it within its
    first second (the replay tells the Pipeline), where a live link waits status_wait_s (5 s) for one."""
    told = _trusted_from_s(run, True, monkeypatch, core)
    waited = _trusted_from_s(run, False, monkeypatch, core)
    assert told < 1.0, told
    assert 5.0 <= waited < 6.0, waited


def test_replay_of_a_dataflash_log_without_status_tells_the_pipeline(tmp_path, monkeypatch):
    """service/replay.run_replay asks the reader: none recorded -> Pipeline.fc_sends_no_status."""
    from service import replay
    seen = []
    monkeypatch.setattr(Pipeline, "fc_sends_no_status", lambda self, why: seen.append(why))
    for name, ekf, typ in (("none.bin", "NKF4", 3), ("ekf3.bin", "XKF4", 3)):
        p = tmp_path / name
        dataflash_with_ekf(p, ekf=ekf, ahrs_ekf_type=typ)
        assert replay.main([str(p), "--site", "47.0,8.0", "--no-progress"]) == 0
    assert seen == ["the log records no FC estimator status"]   # the first only: the second records XKF4


@pytest.mark.parametrize("core", ["core", "python"])
def test_a_status_that_comes_before_the_first_imu_sample_is_not_lost(run, core, monkeypatch):
    """GIVEN the FC's only estimator status (good) arriving before the first IMU sample WHEN the flight goes on
    THEN B trusts the FC from the start: the status is held until an FC time dates it (before: dropped, and the
    FC was untrusted until judged without a status after status_wait_s)."""
    assert _trusted_from_s(run, False, monkeypatch, core, status_first=True) < 1.0
