"""The ArduPilot DataFlash (.bin) reader on a small log packed here by hand (FMT + records, the
format ArduPilot writes: header 0xA3 0x95, message id, little-endian struct; pymavlink has no
writer), read back through pymavlink's DFReader: units, instances, times, the site and the date,
and a replay through the Pipeline whose levelling must give back the packed tilt."""
import csv
import datetime as dt
import json
import math
import struct

import numpy as np
import pytest

from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
from service.logreaders import LogError, open_log
from service.replay import CSV_COLUMNS, main

G0 = 9.80665
# DataFlash format chars -> struct (the subset used here; 'c'/'C' are int16/uint16 x 0.01, 'L' int32 x 1e-7)
_STRUCT = {"Q": "Q", "B": "B", "f": "f", "h": "h", "c": "h", "C": "H", "I": "I", "H": "H", "L": "i"}
FORMATS = {
    "IMU": (129, "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    "MAG": (130, "QBhhh", "TimeUS,I,MagX,MagY,MagZ"),
    "BARO": (131, "QBff", "TimeUS,I,Press,Temp"),
    "ARSP": (132, "QBff", "TimeUS,I,Airspeed,DiffPress"),
    "ATT": (133, "QccC", "TimeUS,Roll,Pitch,Yaw"),
    "GPS": (134, "QBBIHLLf", "TimeUS,I,Status,GMS,GWk,Lat,Lng,Alt"),
}
ROLL_DEG, PITCH_DEG, YAW_DEG = 10.0, -5.0, 350.0
GYRO_BIAS = np.array([0.002, -0.001, 0.0005])
MAG_MGAUSS = (210, -35, 420)
LAT, LON = -35.3623306, 149.1657481
DATE = dt.datetime(2026, 3, 1, 12, 0, 0, tzinfo=dt.timezone.utc)


def _fmt_record(name: str) -> bytes:
    tid, fmt, cols = FORMATS[name]
    length = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
    return struct.pack("<BBBBB4s16s64s", 0xA3, 0x95, 0x80, tid, length, name.encode(), fmt.encode(), cols.encode())


def _record(name: str, *values) -> bytes:
    tid, fmt, _ = FORMATS[name]
    return bytes([0xA3, 0x95, tid]) + struct.pack("<" + "".join(_STRUCT[c] for c in fmt), *values)


def specific_force(roll_deg: float, pitch_deg: float) -> np.ndarray:
    """f in FRD body axes at rest: -C_body_from_nav [0, 0, g]."""
    r, p = math.radians(roll_deg), math.radians(pitch_deg)
    return -G0 * np.array([-math.sin(p), math.sin(r) * math.cos(p), math.cos(r) * math.cos(p)])


def write_dataflash(path, seconds: float = 4.0, imu_hz: float = 200.0, gyro_bias=GYRO_BIAS) -> None:
    gps_s = DATE.timestamp() - 315964800 + 18
    gwk, gms = int(gps_s // 604800), int(round((gps_s % 604800) * 1000))
    f = specific_force(ROLL_DEG, PITCH_DEG)
    out = [_fmt_record(n) for n in FORMATS]
    n = int(seconds * imu_hz)
    t0_us = 5_000_000
    for k in range(n):
        t = t0_us + int(round(k * 1e6 / imu_hz))
        out.append(_record("IMU", t, 0, *gyro_bias, *f))
        out.append(_record("IMU", t + 50, 1, 9.0, 9.0, 9.0, 1.0, 1.0, 1.0))  # a second IMU: ignored
        if k % 4 == 0:
            out.append(_record("MAG", t + 100, 0, *MAG_MGAUSS))
        if k % 20 == 0:
            out.append(_record("ARSP", t + 150, 0, 3.0, 5.5))
            out.append(_record("BARO", t + 200, 0, 95552.5, 21.25))
            out.append(_record("ATT", t + 300, int(ROLL_DEG * 100), int(PITCH_DEG * 100), int(YAW_DEG * 100)))
        if k % 40 == 0:
            out.append(_record("GPS", t + 400, 0, 3 if k >= 40 else 1, gms, gwk, int(LAT * 1e7), int(LON * 1e7), 601.5))
    path.write_bytes(b"".join(out))


@pytest.fixture(scope="module")
def binlog(tmp_path_factory):
    p = tmp_path_factory.mktemp("df") / "flight.bin"
    write_dataflash(p)
    return p


def test_reader_units_instances_and_order(binlog):
    r = open_log(binlog)
    items = list(r.items())
    imu = [i for i in items if isinstance(i, ImuSample)]
    press = [i for i in items if isinstance(i, PressureSample)]
    att = [i for i in items if isinstance(i, FcAttitude)]
    assert len(imu) == 800 and len(press) == 40 and len(att) == 40  # instance 1 left out
    assert r.summary.counts["imu"] == 800
    np.testing.assert_allclose(imu[0].gyro_rad_s, GYRO_BIAS.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(imu[0].accel_m_s2, specific_force(ROLL_DEG, PITCH_DEG).astype(np.float32), rtol=0, atol=0)
    assert imu[0].time_fc_s == pytest.approx(5.0, abs=1e-12) and imu[1].time_fc_s == pytest.approx(5.005, abs=1e-12)
    # the first IMU sample precedes the first MAG: no magnetometer yet (None, never zeros)
    assert imu[0].mag_gauss is None
    np.testing.assert_allclose(imu[1].mag_gauss, np.array(MAG_MGAUSS) * 1e-3, rtol=0, atol=1e-15)
    assert press[0].press_abs_pa == pytest.approx(95552.5) and press[0].temperature_k == pytest.approx(294.4)
    assert press[0].press_diff_pa == pytest.approx(5.5)  # ARSP written 50 us before the BARO
    a = att[0]
    assert math.degrees(a.roll_rad) == pytest.approx(ROLL_DEG, abs=1e-9)
    assert math.degrees(a.pitch_rad) == pytest.approx(PITCH_DEG, abs=1e-9)
    assert math.degrees(a.yaw_rad) == pytest.approx(YAW_DEG - 360.0, abs=1e-9)  # (-pi, pi]
    for cls in (ImuSample, PressureSample, FcAttitude):
        t = np.array([i.time_fc_s for i in items if isinstance(i, cls)])
        assert np.all(np.diff(t) > 0)


def test_site_and_date_from_gps(binlog):
    r = open_log(binlog)
    s = r.site()
    assert s.lat_deg == pytest.approx(LAT, abs=1e-7) and s.lon_deg == pytest.approx(LON, abs=1e-7)
    assert s.alt_m == pytest.approx(601.5) and "status 3" in s.source  # the first (status 1) fix is skipped
    year = 2026 + (DATE - dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)).total_seconds() / (365 * 86400)
    assert r.decimal_year() == pytest.approx(year, abs=1e-6)


def test_replay_levels_on_the_packed_tilt(tmp_path, capsys):
    """Still, no gyro bias: whatever estimator the Pipeline runs holds the packed tilt."""
    log, out, js = tmp_path / "still.bin", tmp_path / "o.csv", tmp_path / "o.json"
    write_dataflash(log, gyro_bias=np.zeros(3))
    assert main([str(log), "--output", str(out), "--json", str(js), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "site from the log's GPS (status 3)" in text and "field model date from the log: 2026.16" in text
    assert any(ln.strip().startswith("levelled: roll 10.00 deg, pitch -5.00 deg") and " at 7.00 s x1" in ln
               for ln in text.splitlines())
    rows = list(csv.reader(out.open()))
    assert rows[0] == CSV_COLUMNS and len(rows) == 201  # 4 s of IMU at the 50 Hz filter rate: a row per output
    levelled = [r for r in rows[1:] if r[2]]
    assert len(levelled) >= 90, "the still 4 s must level (2 s blocks)"
    for r in (levelled[0], levelled[-1]):
        assert float(r[2]) == pytest.approx(ROLL_DEG, abs=1e-4)  # float32 storage of the accel
        assert float(r[3]) == pytest.approx(PITCH_DEG, abs=1e-4)
    assert float(levelled[-1][9]) == pytest.approx(ROLL_DEG, abs=1e-9)
    assert float(levelled[-1][11]) == pytest.approx(YAW_DEG, abs=1e-9)
    s = json.loads(js.read_text())
    assert s["missing_streams"] == [] and s["warnings"] == [] and s["imu_rate_hz"] == pytest.approx(200.0, rel=1e-6)
    assert s["roll_rms_diff_deg"] < 1e-4 and s["pitch_rms_diff_deg"] < 1e-4


def test_not_dataflash_and_no_imu(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"\x00" * 100)
    with pytest.raises(LogError, match="not an ArduPilot DataFlash log"):
        open_log(p)
    p.write_bytes(_fmt_record("BARO") + _record("BARO", 1000, 0, 95552.5, 21.25))
    with pytest.raises(LogError, match="no IMU records"):
        open_log(p)
