"""The log readers on damaged copies of the shared real logs: cut at every 10 %, bits flipped,
fields renamed. Each copy gives either a clear one-line LogError or its samples up to the damage
with the damage said in the summary; never another exception. The readers alone (no Pipeline),
and for the telemetry log a prefix, so that the file stays fast."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mavlink_io.samples import ImuSample, PressureSample
from service.logreaders import LogError, open_log

DATA = Path("/work/shared/data")
LOGS = {"tlog": DATA / "arducopter-flight.tlog", "bin": DATA / "arducopter-rtl-midflight.bin",
        "vtol": DATA / "px4-vtol-airspeed-small.ulg", "quad": DATA / "px4-quad-no-gnss.ulg",
        "bench": DATA / "px4-bench-sample.ulg"}
TLOG_PREFIX_BYTES = 80_000
"""The telemetry log goes through the daemon's whole MAVLink receive path: a prefix keeps it fast."""
MAX_ITEMS_BIG = 3000
"""Items read from a cut copy of the two big ULogs (the cut itself is found when the file is opened)."""


def _bytes(name: str) -> bytes:
    p = LOGS[name]
    if not p.exists():
        pytest.skip(f"shared real log {p} not available")
    data = p.read_bytes()
    return data[:TLOG_PREFIX_BYTES] if name == "tlog" else data


def _read(path: Path, max_items: int | None = None):
    """(items, reader) or (None, LogError text): never any other exception."""
    try:
        r = open_log(path)
        r.site()
        r.decimal_year()
        items = []
        for it in r.items():
            items.append(it)
            if max_items is not None and len(items) >= max_items:
                break
        return items, r
    except LogError as exc:
        text = str(exc)
        assert "\n" not in text and str(path) in text and len(text) < 400, text
        return None, text


@pytest.mark.parametrize("name", list(LOGS))
def test_every_10_percent_cut_is_read_to_the_cut_and_said(name, tmp_path):
    data = _bytes(name)
    ext = LOGS[name].suffix
    big = name in ("quad", "bench")
    read_fully = 0
    for tenth in range(1, 10):
        n = len(data) * tenth // 10
        p = tmp_path / f"cut{tenth}{ext}"
        p.write_bytes(data[:n])
        items, r = _read(p, MAX_ITEMS_BIG if big else None)
        if items is None:
            continue  # e.g. cut before the first IMU record / inside the ULog definitions: one line
        notes = " ".join(r.summary.notes)
        assert "truncated log" in notes, f"{name} cut at {tenth * 10} %: not said ({notes})"
        read_fully += 1
        # the IMU samples before the cut (a short telemetry prefix may hold none: replay says so)
        t = np.array([i.time_fc_s for i in items if type(i) is ImuSample])
        assert np.all(np.isfinite(t)) and (t.size or name == "tlog")
    assert read_fully >= 7, f"{name}: only {read_fully} of 9 cuts readable"


def _flip(data: bytes, positions: list[int], bits: list[int]) -> bytes:
    b = bytearray(data)
    for pos, bit in zip(positions, bits):
        b[pos % len(b)] ^= 1 << bit
    return bytes(b)


@pytest.mark.parametrize("name", ["tlog", "bin", "vtol"])
@settings(max_examples=5, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(flips=st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 7)), min_size=1, max_size=40))
def test_flipped_bits_give_samples_or_one_line(name, flips, tmp_path):
    data = _bytes(name)
    p = tmp_path / f"flipped{LOGS[name].suffix}"
    p.write_bytes(_flip(data, [f[0] for f in flips], [f[1] for f in flips]))
    items, r = _read(p)
    if items is not None:
        for it in items:
            if type(it) is ImuSample:
                assert it.gyro_rad_s.shape == (3,) and it.accel_m_s2.shape == (3,)


@pytest.mark.parametrize("name,old,new,expect", [
    # PX4 renamed the baro temperature: the new name is read, an unknown one leaves it out (said)
    ("vtol", b"baro_temp_celcius", b"ambient_temperature", "temperature"),
    ("vtol", b"baro_temp_celcius", b"baro_temp_unknownx", "no temperature field"),
    # vehicle_magnetometer unusable: the raw sensor_mag instead, said uncalibrated
    ("vtol", b"magnetometer_ga", b"magnetometer_xx", "sensor_mag (uncalibrated"),
    ("vtol", b"gyro_rad", b"gyro_xyz", "sensor_combined has no gyro_rad[0]"),
    ("bin", b"GyrX", b"GyrQ", "the IMU records have no GyrX"),
    ("bin", b"Press", b"Prass", "BARO records have no Press"),
    ("bin", b"DesRoll,Roll,", b"DesRoll,Rxll,", "ATT records have no Roll"),
])
def test_renamed_fields(name, old, new, expect, tmp_path):
    data = _bytes(name)
    assert old in data
    if len(new) != len(old):  # a ULog format definition carries its own length: rewrite it
        data = _rename_ulog_field(data, old, new)
    else:
        data = data.replace(old, new)
    p = tmp_path / f"renamed{LOGS[name].suffix}"
    p.write_bytes(data)
    items, r = _read(p)
    if items is None:
        assert expect in r
        return
    notes = " ".join(r.summary.notes)
    press = [i for i in items if type(i) is PressureSample]
    if expect == "temperature":
        assert press and all(x.temperature_k is not None for x in press)
    elif expect == "no temperature field":
        assert press and all(x.temperature_k is None for x in press) and expect in notes
    elif expect.startswith("sensor_mag"):
        assert expect in notes and any(i.mag_gauss is not None for i in items if type(i) is ImuSample)
    elif expect.startswith("ATT"):
        assert expect in notes and not [i for i in items if type(i).__name__ == "FcAttitude"]
    else:
        assert expect in notes and not press


def _rename_ulog_field(data: bytes, old: bytes, new: bytes) -> bytes:
    """``old`` -> ``new`` inside the ULog 'F' definitions, with each message's size rewritten."""
    out = bytearray(data[:16])
    pos = 16
    while pos + 3 <= len(data):
        size = int.from_bytes(data[pos:pos + 2], "little")
        kind = data[pos + 2]
        payload = data[pos + 3:pos + 3 + size]
        if kind == ord("F"):
            payload = payload.replace(old, new)
        out += len(payload).to_bytes(2, "little") + bytes([kind]) + payload
        pos += 3 + size
    return bytes(out + data[pos:])


def _without(data: bytes, msg_ids: set[int]) -> bytes:
    """A tlog's records minus the frames of ``msg_ids`` (a stream the FC never sent)."""
    from mavlink_io.tlog import TlogReader
    out = []
    for t_s, frame in TlogReader(data):
        mid = frame[5] if frame[0] == 0xFE else frame[7] | frame[8] << 8 | frame[9] << 16
        if mid not in msg_ids:
            out.append(int(round(t_s * 1e6)).to_bytes(8, "big") + frame)
    return b"".join(out)


def test_tlog_missing_streams(tmp_path, capsys):
    """GIVEN a telemetry log without SCALED_PRESSURE THEN no pressure samples and replay names the
    barometer missing; without any IMU message THEN one line, exit 2."""
    from service.replay import main
    data = _bytes("tlog")
    p = tmp_path / "nobaro.tlog"
    p.write_bytes(_without(data, {29}))  # SCALED_PRESSURE
    items, r = _read(p)
    assert items is not None and not [i for i in items if type(i) is PressureSample]
    assert [i for i in items if type(i) is ImuSample]
    p.write_bytes(_without(data, {27, 26, 105, 116, 129}))  # RAW_IMU, SCALED_IMU(1-3), HIGHRES_IMU
    assert main([str(p), "--site", "1,2", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "no IMU samples" in err and err.count("\n") == 1
