"""The log readers on format variants written here (PX4 ULog and ArduPilot DataFlash as their
firmware of different generations writes them): the right samples, the FC's own armed/landed state
and take-offs, the site only where the log says it is valid, and one-line errors where a log
cannot be used; never a traceback."""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from mavlink_io.samples import FcAttitude, FcFlightState, ImuSample, PressureSample
from service.logreaders import FlightStateTrack, open_log
from service.replay import main

G0 = 9.80665
_ULOG_TYPES = {"uint64_t": "Q", "int64_t": "q", "uint32_t": "I", "int32_t": "i", "uint16_t": "H",
               "int16_t": "h", "uint8_t": "B", "int8_t": "b", "bool": "?", "float": "f", "double": "d"}


def _ulog_msg(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


class UlogWriter:
    """``topic(name, [(type, field), ...])`` then ``add(name, values..., multi_id=)``; ``bytes()``.

    A field type is a C type of _ULOG_TYPES, with ``[n]`` for arrays; the first field must be
    ``uint64_t timestamp`` (microseconds)."""

    def __init__(self) -> None:
        self.formats: dict[str, list] = {}
        self.subs: dict[tuple[str, int], int] = {}
        self.data: list[tuple[int, int, bytes]] = []  # (timestamp, order, message)

    def topic(self, name: str, fields: list[tuple[str, str]]) -> None:
        self.formats[name] = fields

    def _struct(self, name: str) -> str:
        out = "<"
        for typ, _ in self.formats[name]:
            base, _, n = typ.partition("[")
            out += (n.rstrip("]") if n else "") + _ULOG_TYPES[base]
        return out

    def add(self, name: str, *values, multi_id: int = 0) -> None:
        key = (name, multi_id)
        if key not in self.subs:
            self.subs[key] = len(self.subs)
        flat = []
        for v in values:
            flat.extend(v if isinstance(v, (list, tuple)) else [v])
        payload = struct.pack("<H", self.subs[key]) + struct.pack(self._struct(name), *flat)
        self.data.append((int(values[0]), len(self.data), _ulog_msg(b"D", payload)))

    def bytes(self) -> bytes:
        out = [b"ULog\x01\x12\x35", bytes([1]), struct.pack("<Q", 0)]
        for name, fields in self.formats.items():
            text = f"{name}:" + "".join(f"{t} {f};" for t, f in fields)
            out.append(_ulog_msg(b"F", text.encode()))
        for (name, multi_id), msg_id in self.subs.items():
            out.append(_ulog_msg(b"A", struct.pack("<BH", multi_id, msg_id) + name.encode()))
        out += [m for _, _, m in sorted(self.data)]
        return b"".join(out)


# --- ArduPilot DataFlash -------------------------------------------------------------------------

_DF_STRUCT = {"Q": "Q", "q": "q", "B": "B", "b": "b", "f": "f", "h": "h", "H": "H", "c": "h", "C": "H",
              "I": "I", "i": "i", "L": "i", "e": "i", "E": "I", "M": "B", "N": "16s"}


class DataflashWriter:
    """``fmt(type_id, name, format, "Col1,Col2")`` then ``rec(name, values...)``; ``bytes()``.
    Values of c/C/e/E fields are given scaled (x100), of L fields as 1e-7 degree integers."""

    def __init__(self) -> None:
        self.formats: dict[str, tuple[int, str]] = {}
        self.out: list[bytes] = []

    def fmt(self, type_id: int, name: str, fmt: str, columns: str) -> None:
        self.formats[name] = (type_id, fmt)
        length = 3 + struct.calcsize("<" + "".join(_DF_STRUCT[c] for c in fmt))
        self.out.append(struct.pack("<BBBBB4s16s64s", 0xA3, 0x95, 0x80, type_id, length, name.encode(),
                                    fmt.encode(), columns.encode()))

    def rec(self, name: str, *values) -> None:
        type_id, fmt = self.formats[name]
        self.out.append(bytes([0xA3, 0x95, type_id]) + struct.pack("<" + "".join(_DF_STRUCT[c] for c in fmt),
                                                                 *values))

    def bytes(self) -> bytes:
        return b"".join(self.out)


# --- helpers -------------------------------------------------------------------------------------

ROLL_DEG, PITCH_DEG = 10.0, -5.0


def specific_force(roll_deg: float, pitch_deg: float) -> list[float]:
    """f in FRD body axes at rest: -C_body_from_nav [0, 0, g]."""
    r, p = math.radians(roll_deg), math.radians(pitch_deg)
    return [G0 * math.sin(p), -G0 * math.sin(r) * math.cos(p), -G0 * math.cos(r) * math.cos(p)]


def _one_line_error(capsys, argv) -> str:
    rc = main([*map(str, argv), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err
    return err


T0_S = 10.0
MAG_A_GA, MAG_B_GA = (0.21, -0.03, 0.42), (0.5, 0.5, 0.5)


def px4_ulog(path, *, seconds=4.0, imu_hz=200.0, mag_hz=2.0, mag_ids=(1, 2), temp_field="ambient_temperature",
             home=None, gyro_field="gyro_rad", with_sensor_combined=True, raw_hz=1.0, status_flags=None) -> None:
    """A still, tilted vehicle: sensor_combined at imu_hz; vehicle_magnetometer at mag_hz as instances
    ``mag_ids`` (the first MAG_A_GA, the others MAG_B_GA); vehicle_air_data with its temperature in
    ``temp_field`` (None: no temperature); vehicle_attitude; home_position = (valid_hpos, valid_alt)
    or None; vehicle_status disarmed -> armed at T0+1 s; vehicle_land_detected landed -> in air at
    T0+2.5 s (the FC's own take-off); estimator_status at 5 Hz with ``status_flags`` (None: not logged)."""
    w = UlogWriter()
    if with_sensor_combined:
        w.topic("sensor_combined", [("uint64_t", "timestamp"), ("float[3]", gyro_field),
                                    ("uint32_t", "gyro_integral_dt"),
                                    ("int32_t", "accelerometer_timestamp_relative"), ("float[3]", "accelerometer_m_s2"),
                                    ("uint32_t", "accelerometer_integral_dt")])
    w.topic("sensor_gyro", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float", "x"),
                            ("float", "y"), ("float", "z")])
    w.topic("sensor_accel", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float", "x"),
                             ("float", "y"), ("float", "z")])
    w.topic("vehicle_magnetometer", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                                     ("uint32_t", "device_id"), ("float[3]", "magnetometer_ga")])
    air = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float", "baro_alt_meter"),
           ("float", "baro_pressure_pa")] + ([("float", temp_field)] if temp_field else [])
    w.topic("vehicle_air_data", air)
    w.topic("vehicle_attitude", [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[4]", "q")])
    w.topic("home_position", [("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"), ("float", "alt"),
                              ("bool", "valid_alt"), ("bool", "valid_hpos")])
    w.topic("vehicle_status", [("uint64_t", "timestamp"), ("uint8_t", "arming_state")])
    w.topic("vehicle_land_detected", [("uint64_t", "timestamp"), ("bool", "landed"), ("bool", "maybe_landed")])
    if status_flags is not None:
        w.topic("estimator_status", [("uint64_t", "timestamp"), ("uint16_t", "solution_status_flags"),
                                     ("float", "mag_test_ratio")])
    f = specific_force(ROLL_DEG, PITCH_DEG)
    us = lambda t: int(round(t * 1e6))  # noqa: E731
    for k in range(int(seconds * imu_hz)):
        t = us(T0_S + k / imu_hz)
        if with_sensor_combined:
            w.add("sensor_combined", t, [0.0, 0.0, 0.0], 5000, 0, f, 5000)
        else:  # raw sensor topics only (PX4's default profile logs them at 1 Hz)
            if k % int(imu_hz / raw_hz) == 0:
                w.add("sensor_gyro", t, t, 0.0, 0.0, 0.0)
                w.add("sensor_accel", t, t, *f)
        if k % 10 == 0:
            w.add("vehicle_air_data", t + 100, t + 100, 400.0, 95552.5, *([21.5] if temp_field else []))
            # q of roll 10, pitch -5, yaw 0 (ZYX): w, x, y, z
            r, p = math.radians(ROLL_DEG) / 2, math.radians(PITCH_DEG) / 2
            q = [math.cos(r) * math.cos(p), math.sin(r) * math.cos(p), math.cos(r) * math.sin(p),
                 -math.sin(r) * math.sin(p)]
            w.add("vehicle_attitude", t + 200, t + 200, q)
    n_mag = int(seconds * mag_hz)
    for k in range(n_mag):
        t = us(T0_S + k / mag_hz + 0.001)
        for i, mid in enumerate(mag_ids):
            w.add("vehicle_magnetometer", t, t, 7, list(MAG_A_GA if i == 0 else MAG_B_GA), multi_id=mid)
    if home is not None:
        w.add("home_position", us(T0_S + 0.5), 47.397742, 8.545594, 488.0, home[1], home[0])
    for ts, state in ((0.0, 1), (1.0, 2), (2.0, 2), (3.0, 2)):
        w.add("vehicle_status", us(T0_S + ts + 0.002), state)
    for ts, landed in ((0.0, True), (2.5, False), (3.5, False)):
        w.add("vehicle_land_detected", us(T0_S + ts + 0.003), landed, landed)
    if status_flags is not None:
        for k in range(int(seconds * 5)):
            w.add("estimator_status", us(T0_S + 0.2 * k + 0.004), status_flags, 0.25)
    path.write_bytes(w.bytes())


# --- PX4 ULog --------------------------------------------------------------------------------------

def test_ulog_renamed_temperature_mag_by_instance_at_2_hz_and_the_fcs_takeoff(tmp_path):
    """GIVEN a newer PX4's ULog: baro temperature as `ambient_temperature`, the magnetometer at 2 Hz
    logged as instances 1 and 2 only, the land detector and the arming state
    WHEN it is read THEN the temperature is used, instance 1's field is held onto the IMU samples
    at most 0.5 s, and the FC's own state and take-off come out of its records."""
    p = tmp_path / "new.ulg"
    px4_ulog(p)
    r = open_log(p)
    items = list(r.items())
    imu = [i for i in items if type(i) is ImuSample]
    press = [i for i in items if type(i) is PressureSample]
    assert len(imu) == 800 and len(press) == 80
    assert imu[1].time_fc_s == pytest.approx(T0_S + 0.005, abs=1e-9)
    np.testing.assert_allclose(imu[0].accel_m_s2, np.float32(specific_force(ROLL_DEG, PITCH_DEG)), rtol=0, atol=0)
    assert press[0].temperature_k == pytest.approx(21.5 + 273.15) and press[0].press_abs_pa == pytest.approx(95552.5)
    # which IMU samples carry a magnetometer: the last 2 Hz sample at most 0.5 s before
    t_imu = np.array([s.time_fc_s for s in imu])
    t_mag = T0_S + np.arange(8) / 2.0 + 0.001
    j = np.searchsorted(t_mag, t_imu, side="right") - 1
    expect = (j >= 0) & (t_imu - t_mag[np.maximum(j, 0)] <= 0.5 + 1e-9)
    got = np.array([s.mag_gauss is not None for s in imu])
    assert np.array_equal(got, expect) and 0 < got.sum() < len(imu)
    assert all(np.allclose(s.mag_gauss, MAG_A_GA, atol=1e-7) for s in imu if s.mag_gauss is not None)
    notes = " ".join(r.summary.notes)
    assert "vehicle_magnetometer: instance 1 used of 2 logged" in notes and "2.0 Hz" in notes
    # the FC's own armed / landed state, carried record to record
    states = [(round(s.time_fc_s - T0_S, 3), s.armed, s.landed) for s in items if type(s) is FcFlightState]
    assert states == [(0.002, False, None), (0.003, False, True), (1.002, True, True), (2.002, True, True),
                      (2.503, True, False), (3.002, True, False), (3.503, True, False)]
    assert r.takeoff_times_s() == [pytest.approx(T0_S + 2.503, abs=1e-9)]
    att = [i for i in items if type(i) is FcAttitude]
    assert math.degrees(att[0].roll_rad) == pytest.approx(ROLL_DEG, abs=1e-4)


def test_ulog_invalid_home_position_is_no_site(tmp_path, capsys):
    """GIVEN home_position with valid_hpos = 0 (no GNSS fix) WHEN replayed without --site THEN exit 2:
    give --site; with valid_hpos the site is taken, its altitude only with valid_alt."""
    p = tmp_path / "nofix.ulg"
    px4_ulog(p, home=(False, False))
    assert open_log(p).site() is None
    err = _one_line_error(capsys, [p])
    assert "give --site" in err
    px4_ulog(p, home=(True, False))
    s = open_log(p).site()
    assert (s.lat_deg, s.lon_deg, s.alt_m) == (pytest.approx(47.397742), pytest.approx(8.545594), 0.0)
    assert "altitude not valid" in s.source
    px4_ulog(p, home=(True, True))
    assert open_log(p).site().alt_m == pytest.approx(488.0)


def test_ulog_replay_with_site_gives_the_logs_own_takeoff(tmp_path, capsys):
    p, js = tmp_path / "f.ulg", tmp_path / "s.json"
    px4_ulog(p, seconds=3.0, temp_field="baro_temp_celcius")
    assert main([str(p), "--site", "47.4,8.5", "--json", str(js), "--no-progress"]) == 0
    import json
    s = json.loads(js.read_text())
    assert s["log_takeoff_times_s"] == [pytest.approx(T0_S + 2.503, abs=1e-9)]
    assert s["fc_flight_state_records"] == 7 and s["pressure_samples"] == 60
    assert "the log's own take-off" in capsys.readouterr().out


def test_ulog_without_a_usable_imu_says_why_in_one_line(tmp_path, capsys):
    p = tmp_path / "renamed.ulg"
    px4_ulog(p, seconds=1.0, gyro_field="gyro_rad_s")
    err = _one_line_error(capsys, [p, "--site", "1,2"])
    assert "sensor_combined has no gyro_rad[0]" in err
    px4_ulog(p, seconds=3.0, with_sensor_combined=False)
    err = _one_line_error(capsys, [p, "--site", "1,2"])
    assert "no sensor_combined" in err and "1.0 Hz only" in err


def test_ulog_imu_from_raw_sensor_topics(tmp_path):
    """GIVEN no sensor_combined but sensor_gyro/sensor_accel at the full rate (high-rate profile)
    THEN the IMU comes from them, the accelerometer held onto the gyro times, and it is said."""
    p = tmp_path / "raw.ulg"
    px4_ulog(p, seconds=1.0, with_sensor_combined=False, raw_hz=200.0)
    r = open_log(p)
    imu = [i for i in r.items() if type(i) is ImuSample]
    assert len(imu) == 200 and imu[0].source == "sensor_gyro"
    np.testing.assert_allclose(imu[-1].accel_m_s2, np.float32(specific_force(ROLL_DEG, PITCH_DEG)), rtol=0, atol=0)
    assert any("IMU from sensor_gyro + sensor_accel" in n for n in r.summary.notes)


def test_ulog_without_a_temperature_field(tmp_path):
    p = tmp_path / "notemp.ulg"
    px4_ulog(p, seconds=1.0, temp_field=None)
    r = open_log(p)
    press = [i for i in r.items() if type(i) is PressureSample]
    assert len(press) == 20 and all(x.temperature_k is None for x in press)
    assert any("no temperature field" in n for n in r.summary.notes)


# --- ArduPilot DataFlash -----------------------------------------------------------------------------

def old_dataflash(path) -> None:
    """An ArduCopter 3.2-era log: TimeMS, no instance field (IMU2/MAG2 separate), GPS with Week and
    TimeMS of week, EV without a time."""
    w = DataflashWriter()
    w.fmt(129, "IMU", "Iffffff", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    w.fmt(130, "IMU2", "Iffffff", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    w.fmt(131, "MAG", "Ihhhhhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ")
    w.fmt(132, "BARO", "Iffcf", "TimeMS,Alt,Press,Temp,CRt")
    w.fmt(133, "ATT", "IccccCC", "TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    w.fmt(134, "GPS", "BIHBcLLeeEefI", "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,VZ,T")
    w.fmt(135, "EV", "B", "Id")
    f = specific_force(ROLL_DEG, PITCH_DEG)
    for k in range(200):  # 50 Hz for 4 s
        t_ms = 20000 + 20 * k
        w.rec("IMU", t_ms, 0.001, 0.0, 0.0, *f)
        w.rec("IMU2", t_ms, 9.0, 9.0, 9.0, 1.0, 1.0, 1.0)
        if k % 5 == 0:
            w.rec("MAG", t_ms + 1, 210, -35, 420, 0, 0, 0, 0, 0, 0)
            w.rec("BARO", t_ms + 2, 0.0, 95552.5, 2125, 0.0)
            w.rec("ATT", t_ms + 3, 0, int(ROLL_DEG * 100), 0, int(PITCH_DEG * 100), 0, 35000)
            w.rec("GPS", 3 if k >= 50 else 1, 302400000 + t_ms, 1850, 9, 120, int(-35.3623306e7),
                  int(149.1657481e7), 0, 60150, 0, 0, 0.0, t_ms)
        if k == 20:
            w.rec("EV", 10)  # armed
        if k == 60:
            w.rec("EV", 28)  # not landed: the take-off
    path.write_bytes(w.bytes())


def test_dataflash_old_layout_timems(tmp_path):
    p = tmp_path / "old.bin"
    old_dataflash(p)
    r = open_log(p)
    items = list(r.items())
    imu = [i for i in items if type(i) is ImuSample]
    assert len(imu) == 200 and imu[0].time_fc_s == pytest.approx(20.0) and imu[1].time_fc_s == pytest.approx(20.02)
    assert all(i.gyro_rad_s[0] == pytest.approx(0.001) for i in imu)  # IMU, never IMU2
    assert imu[1].mag_gauss is not None and np.allclose(imu[1].mag_gauss, [0.21, -0.035, 0.42])
    press = [i for i in items if type(i) is PressureSample]
    assert len(press) == 40 and press[0].temperature_k == pytest.approx(21.25 + 273.15)
    s = r.site()
    assert s.lat_deg == pytest.approx(-35.3623306) and s.alt_m == pytest.approx(601.5) and "status 3" in s.source
    # GPS week 1850 + 302.4 s + TimeMS: 2015-06-21 -> 2015.47
    assert r.decimal_year() == pytest.approx(2015.47, abs=0.01)
    notes = " ".join(r.summary.notes)
    assert "TimeMS" in notes and "IMU: IMU used of IMU, IMU2" in notes
    # EV has no time in old logs: the last record's time; armed, then in the air
    assert r.takeoff_times_s() == [pytest.approx(21.203)]
    states = [(s.armed, s.landed) for s in items if type(s) is FcFlightState]
    assert states == [(True, None), (True, False)]


def new_dataflash(path, events, *, gps_status=3, rename=None, cut=None, seconds=4.0) -> bytes:
    """An ArduPilot 4.x log: TimeUS, instance field I (IMU 0 and 1), EV/ARM records at given times."""
    w = DataflashWriter()
    cols = {"IMU": "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ", "BARO": "TimeUS,I,Press,Temp"}
    for k, (a, b) in (rename or {}).items():
        cols[k] = cols[k].replace(a, b)
    w.fmt(129, "IMU", "QBffffff", cols["IMU"])
    w.fmt(131, "BARO", "QBff", cols["BARO"])
    w.fmt(134, "GPS", "QBBIHLLf", "TimeUS,I,Status,GMS,GWk,Lat,Lng,Alt")
    w.fmt(135, "EV", "QB", "TimeUS,Id")
    w.fmt(136, "ARM", "QHIbB", "TimeUS,ArmState,ArmChecks,Forced,Method")
    f = specific_force(ROLL_DEG, PITCH_DEG)
    ev = sorted(events)
    for k in range(int(100 * seconds)):  # 100 Hz
        t = 5_000_000 + 10_000 * k
        while ev and ev[0][0] * 1e6 <= t:
            t_ev, kind, val = ev.pop(0)
            if kind == "EV":
                w.rec("EV", int(t_ev * 1e6), val)
            else:
                w.rec("ARM", int(t_ev * 1e6), val, 0, 0, 0)
        w.rec("IMU", t, 1, 9.0, 9.0, 9.0, 1.0, 1.0, 1.0)
        w.rec("IMU", t + 10, 0, 0.0, 0.0, 0.0, *f)
        if k % 10 == 0:
            w.rec("BARO", t + 20, 0, 95552.5, 21.25)
            w.rec("GPS", t + 30, 0, gps_status, 1000 * k, 2400, int(52.0381699e7), int(5.1448234e7), 3.5)
    data = w.bytes()
    path.write_bytes(data[:cut] if cut else data)
    return data


FLIGHTS = [(5.5, "ARM", 1), (5.5, "EV", 10), (6.0, "EV", 28), (7.0, "EV", 18), (7.5, "EV", 11),
           (7.5, "ARM", 0), (8.0, "EV", 10), (8.5, "EV", 28)]


def test_dataflash_instances_and_two_flights(tmp_path):
    p = tmp_path / "new.bin"
    new_dataflash(p, FLIGHTS)
    r = open_log(p)
    items = list(r.items())
    imu = [i for i in items if type(i) is ImuSample]
    assert len(imu) == 400 and all(np.all(i.gyro_rad_s == 0.0) for i in imu)  # instance 0 only
    assert "IMU: IMU instance 0 used of 0, 1" in " ".join(r.summary.notes)
    assert r.takeoff_times_s() == [pytest.approx(6.0), pytest.approx(8.5)]
    states = [(round(s.time_fc_s, 3), s.armed, s.landed) for s in items if type(s) is FcFlightState]
    assert states[:3] == [(5.5, True, None), (5.5, True, None), (6.0, True, False)]
    assert (7.0, True, True) in states and (7.5, False, True) in states and states[-1] == (8.5, True, False)


def test_dataflash_that_starts_in_flight_is_read_and_replayed_as_started_in_flight(tmp_path, capsys):
    """GIVEN a log whose logging began in the air: its first state records are a landing (EV 18) and
    a disarm (EV 11), with no arming or take-off before them (arducopter-rtl-midflight.bin's shape)
    WHEN read THEN the first item is the state the FC had from the start (armed, in the air), the
    notes say why, and the log has no take-off of its own
    WHEN replayed THEN the run is started in flight (no levelling, no launch), never a take-off."""
    import json
    p = tmp_path / "midflight.bin"
    new_dataflash(p, [(8.0, "EV", 18), (8.5, "EV", 11)])
    r = open_log(p)
    items = list(r.items())
    assert type(items[0]) is FcFlightState and (items[0].armed, items[0].landed) == (True, False)
    assert items[0].time_fc_s == pytest.approx(5.0)
    states = [(round(s.time_fc_s, 3), s.armed, s.landed) for s in items if type(s) is FcFlightState]
    assert states == [(5.0, True, False), (8.0, True, True), (8.5, False, True)]
    assert r.takeoff_times_s() == []
    assert any("starts armed and in the air" in n and "landed at 8.0 s" in n and "disarmed at 8.5 s" in n
               for n in r.summary.notes)
    j = tmp_path / "s.json"
    assert main([str(p), "--json", str(j), "--no-progress"]) == 0
    capsys.readouterr()
    summ = json.loads(j.read_text())
    assert [(x["phase"], round(x["from_time_s"], 2)) for x in summ["phases"]] == [("pre-launch", 5.0),
                                                                                  ("in-flight", 6.02)]
    kinds = {e["kind"]: e["reason"] for e in summ["event_reasons"]}
    assert kinds["started_in_flight"].startswith("FC armed, the FC reports in the air (landed state)")
    assert "takeoff" not in kinds and "launch_unlevelled" not in kinds
    # the contrast: a log that arms first starts on the ground (no start state is inferred)
    new_dataflash(p, FLIGHTS)
    first = next(i for i in open_log(p).items() if type(i) is FcFlightState)
    assert (first.time_fc_s, first.armed, first.landed) == (pytest.approx(5.5), True, None)


def test_dataflash_no_3d_fix_needs_site(tmp_path, capsys):
    p = tmp_path / "nofix.bin"
    new_dataflash(p, [], gps_status=2)
    assert open_log(p).site() is None
    assert "give --site" in _one_line_error(capsys, [p])


def test_dataflash_truncated_damaged_and_renamed(tmp_path, capsys):
    p = tmp_path / "x.bin"
    data = new_dataflash(p, FLIGHTS)
    full = [i for i in open_log(p).items() if type(i) is ImuSample]
    # cut in the middle of a record: read to the cut, said
    p.write_bytes(data[:len(data) // 2 + 7])
    r = open_log(p)
    cut = [i for i in r.items() if type(i) is ImuSample]
    assert 150 < len(cut) < 250 and any("incomplete record (truncated log)" in n for n in r.summary.notes)
    # garbage between records: skipped, said, nothing else lost
    i = data.index(b"\xa3\x95\x81", len(data) // 3)
    junk = bytes(np.random.default_rng(7).integers(0, 0xA2, 41, dtype=np.uint8))
    p.write_bytes(data[:i] + junk + data[i:])
    r = open_log(p)
    assert len([i for i in r.items() if type(i) is ImuSample]) == len(full)
    assert any("41 damaged bytes skipped" in n for n in r.summary.notes)
    # renamed fields: the IMU unusable (one line, exit 2), the barometer left out and said
    new_dataflash(p, [], rename={"IMU": ("GyrX", "GyrQ")})
    assert "the IMU records have no GyrX" in _one_line_error(capsys, [p, "--site", "1,2"])
    new_dataflash(p, [], rename={"BARO": ("Press", "Prss")})
    r = open_log(p)
    assert not [i for i in r.items() if type(i) is PressureSample]
    assert any("BARO records have no Press: BARO not used" in n for n in r.summary.notes)
    new_dataflash(p, [], rename={"IMU": ("TimeUS", "TimeXS")})
    assert "no TimeUS or TimeMS" in _one_line_error(capsys, [p, "--site", "1,2"])


# --- the FC's own take-offs --------------------------------------------------------------------------

@pytest.mark.parametrize("records,takeoffs", [
    # starts in the air: no take-off until it has landed
    ([(0, None, False), (1, None, True), (2, None, False)], [2]),
    ([(0, True, None), (1, None, False)], []),  # armed state at the start (not an arming): unknown ground
    ([(0, False, None), (1, True, None), (2, None, False)], [2]),  # armed after disarmed: on the ground
    ([(0, False, True), (1, True, None), (2, None, False), (3, None, True), (4, None, False)], [2, 4]),
    ([(0, False, True), (1, None, False)], []),  # moved while disarmed: no take-off
])
def test_flight_state_takeoffs(records, takeoffs):
    track = FlightStateTrack()
    for t, armed, landed in records:
        track.update(t, armed=armed, landed=landed)
    assert track.takeoffs_s == takeoffs


# --- MAVLink telemetry log -----------------------------------------------------------------------------

def test_tlog_landed_state_and_the_fcs_takeoff(tmp_path):
    """GIVEN a telemetry log with the FC's HEARTBEAT (armed bit) and EXTENDED_SYS_STATE
    WHEN read THEN FcFlightState follows landed_state with the armed bit, at FC time, and the
    log's own take-off is the first in-air state after arming."""
    import os
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega as mav
    m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    t_unix0, out = 1_700_000_000.0, []

    def rec(t_s, msg):
        out.append(struct.pack(">Q", int(round((t_unix0 + t_s) * 1e6))) + msg.pack(m))
    f = specific_force(0.0, 0.0)
    for k in range(300):  # 50 Hz for 6 s
        t = k * 0.02
        if k % 25 == 0:
            armed = t >= 2.0
            rec(t, mav.MAVLink_heartbeat_message(2, 3, 128 if armed else 0, 0, 4 if armed else 3, 3))
            landed_state = 1 if t < 3.0 else 2
            rec(t + 0.001, mav.MAVLink_extended_sys_state_message(0, landed_state))
        rec(t + 0.002, mav.MAVLink_raw_imu_message(int((100.0 + t) * 1e6), int(f[0] * 1000 / G0),
                                                   int(f[1] * 1000 / G0), int(f[2] * 1000 / G0), 0, 0, 0, 200, 0, 400))
    p = tmp_path / "f.tlog"
    p.write_bytes(b"".join(out))
    r = open_log(p)
    items = list(r.items())
    # the landed state as the daemon's link gives it (armed: the HEARTBEAT's, or None when the link
    # decodes EXTENDED_SYS_STATE itself and leaves armed to the HEARTBEAT)
    states = [(s.armed, s.landed) for s in items if type(s) is FcFlightState]
    assert [x[1] for x in states] == [True] * 6 + [False] * 6
    assert {x[0] for x in states} <= {None, False, True}
    # take-off at the first IN_AIR state (receive time 3.001 s: FC time of the last RAW_IMU + 0.019 s)
    assert r.takeoff_times_s() == [pytest.approx(100.0 + 2.98 + 0.019, abs=1e-6)]


def test_dataflash_arduplane_stat_is_flying(tmp_path):
    """ArduPlane's STAT (isFlying, Armed), logged continuously: a state change only, one take-off."""
    w = DataflashWriter()
    w.fmt(129, "IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    w.fmt(140, "STAT", "QBfBBBBBB", "TimeUS,isFlying,isFlyProb,Armed,Safety,Crash,Still,Stage,Hit")
    f = specific_force(0.0, 0.0)
    for k in range(300):  # 100 Hz for 3 s; STAT at 10 Hz
        t = 1_000_000 + 10_000 * k
        w.rec("IMU", t, 0, 0.0, 0.0, 0.0, *f)
        if k % 10 == 0:
            w.rec("STAT", t + 5, int(k >= 200), 0.0, int(k >= 100), 0, 0, 0, 0, 0)
    p = tmp_path / "plane.bin"
    p.write_bytes(w.bytes())
    r = open_log(p)
    states = [(round(s.time_fc_s, 6), s.armed, s.landed) for s in r.items() if type(s) is FcFlightState]
    assert states == [(1.000005, False, True), (2.000005, True, True), (3.000005, True, False)]
    assert r.takeoff_times_s() == [pytest.approx(3.000005)]
