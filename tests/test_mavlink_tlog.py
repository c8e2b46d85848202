"""A real ArduCopter flight (telemetry log recorded over a radio) through the link's receive path:
decoding, units, filtering, bad CRC counting and a real FC reboot in the middle of the log."""
from pathlib import Path

import numpy as np
import pytest

from mavlink_io.link import LinkEvent
from mavlink_io.samples import FcAttitude, FcEkfStatus, ImuSample, PressureSample
from mavlink_io.tlog import TlogReader, read_tlog, replay_tlog

TLOG = Path("/work/shared/data/arducopter-flight.tlog")
pytestmark = pytest.mark.skipif(not TLOG.exists(), reason="shared real log not available")
G0 = 9.80665


@pytest.fixture(scope="module")
def replay():
    items, link = replay_tlog(TLOG)
    return list(items), link


def test_tlog_reader_reads_every_record():
    reader = TlogReader(TLOG.read_bytes())
    n = sum(1 for _ in reader)
    assert n == reader.records and n > 75_000 and reader.skipped_bytes == 0
    t0, frame = next(read_tlog(TLOG))
    assert 1.4e9 < t0 < 1.5e9 and frame[0] in (0xFE, 0xFD)


def test_real_flight_decodes(replay):
    items, link = replay
    assert link.fc_autopilot == "ardupilot" and (link.target_system, link.target_component) == (1, 1)
    imu = [i for i in items if isinstance(i, ImuSample)]
    press = [i for i in items if isinstance(i, PressureSample)]
    att = [i for i in items if isinstance(i, FcAttitude)]
    # every RAW_IMU of the autopilot becomes a sample (SCALED_IMU2 is a second IMU: not mixed in)
    assert len(imu) == link.stats.messages_by_type["RAW_IMU"] == 2856
    assert {i.source for i in imu} == {"RAW_IMU"}
    assert len(press) == 2855 and len(att) == 2829
    assert any(isinstance(i, FcEkfStatus) for i in items)
    # first RAW_IMU of the log: xacc 39, yacc -29, zacc -991 mG; gyro -1, 2, -2 mrad/s; mag -20, 148, -609 mG
    np.testing.assert_allclose(imu[0].accel_m_s2, np.array([39, -29, -991]) * G0 / 1000, rtol=0, atol=1e-12)
    np.testing.assert_allclose(imu[0].gyro_rad_s, [-0.001, 0.002, -0.002], rtol=0, atol=1e-15)
    np.testing.assert_allclose(imu[0].mag_gauss, [-0.020, 0.148, -0.609], rtol=0, atol=1e-15)
    assert imu[0].time_fc_s == pytest.approx(44.917593, abs=1e-9)
    # at rest before take-off: |f| = g
    assert np.mean([np.linalg.norm(s.accel_m_s2) for s in imu[:20]]) == pytest.approx(G0, rel=0.005)
    assert press[0].press_abs_pa == pytest.approx(95552.496, abs=1e-2)  # 955.52 hPa: Canberra, ~600 m
    assert press[0].temperature_k == pytest.approx(273.15 + 21.28, abs=1e-9)


def test_real_flight_mag_norm_matches_wmm(replay):
    """The FC-calibrated RAW_IMU field, in gauss, against WMM2015 at the log's GPS position."""
    from pygeomag import GeoMag
    from pygeomag.wmm.wmm_2015v2 import WMM_2015v2
    f_nt = GeoMag(coefficients_data=WMM_2015v2).calculate(glat=-35.3623, glon=149.1657, alt=0.6, time=2015.52).f
    items, _ = replay
    mags = np.array([i.mag_gauss for i in items if isinstance(i, ImuSample) and i.mag_gauss is not None])
    assert np.median(np.linalg.norm(mags, axis=1)) == pytest.approx(f_nt * 1e-5, rel=0.01)  # 1 G = 1e5 nT


def test_real_flight_reboot_and_monotonic_time(replay):
    items, link = replay
    reboots = [i for i in items if isinstance(i, LinkEvent) and i.kind == "fc_reboot"]
    assert len(reboots) == 1 and "279.402 s to 18.951 s" in reboots[0].detail
    for cls in (ImuSample, PressureSample, FcAttitude):
        t = np.array([i.time_fc_s for i in items if isinstance(i, cls)])
        assert np.all(np.diff(t) > 0), cls.__name__
    kinds = [i.kind for i in items if isinstance(i, LinkEvent)]
    rr = [i for i in items if isinstance(i, LinkEvent) and i.kind == "rates_requested"]
    assert kinds[0] == "autopilot_detected" and any("FC rebooted" in e.detail for e in rr)


def test_real_flight_stats(replay):
    _, link = replay
    d = link.stats.as_dict()
    assert d["crc_errors"] == 1314  # radio-corrupted frames: pymavlink's BAD_DATA count for this log
    assert d["foreign_messages"] >= 4500  # the GCS (255, 0) and the radio (51, 68)
    assert d["parser_errors"] == 0 and d["non_finite_rejects_total"] == 0
    assert d["seq_lost"] > 0  # a radio link loses packets
