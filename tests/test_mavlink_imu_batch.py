"""RAW_IMU decoded as one typed array (mavlink_io/imu_batch.py, issue 19 item 3's input side) gives
exactly what the per-message path gives: pymavlink's parse + decode.decode_raw_imu, bit for bit,
including MAVLink 2's cut trailing zero bytes and a missing magnetometer (None there, NaN here)."""
from __future__ import annotations

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from mavlink_io.decode import decode_raw_imu
from mavlink_io.imu_batch import RAW_IMU_CRC_EXTRA, RAW_IMU_ID, ImuBatch, raw_imu_records


def _frames(n: int, seed: int = 7):
    rng = np.random.default_rng(seed)
    fc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    out = []
    for k in range(n):
        v = rng.integers(-32768, 32768, size=9)
        if k % 5 == 0:
            v[6:] = 0  # no compass
        imu_id, temp = (0, 0) if k % 3 == 0 else (int(rng.integers(0, 3)), int(rng.integers(-4000, 8000)))
        msg = fc.raw_imu_encode(1_000_000 + 2500 * k + int(rng.integers(0, 2**40)), *map(int, v), imu_id, temp)
        out.append(msg.pack(fc))
    return out


def test_batch_rows_equal_the_per_message_decode_bit_for_bit():
    # GIVEN 500 RAW_IMU frames, some without a compass, some with their payload cut short
    frames = _frames(500)
    parser = mav.MAVLink(None)
    msgs = [parser.parse_char(f) for f in frames]
    payloads = [f[10:10 + f[1]] for f in frames]
    assert min(len(p) for p in payloads) < 29  # MAVLink 2 truncation is exercised
    assert mav.MAVLINK_MSG_ID_RAW_IMU == RAW_IMU_ID and mav.MAVLink_raw_imu_message.crc_extra == RAW_IMU_CRC_EXTRA
    # WHEN decoded both ways (the batch decode at once, and in small batches: its Python path)
    rec, usec = raw_imu_records(payloads, time_rx_s=12.5)
    cuts = np.cumsum([0] + [1, 2, 3, 4, 5, 6, 7, 8] * 14)[:-1]   # 504 > 500: every payload covered
    small = [raw_imu_records(payloads[a:b], 12.5) for a, b in zip(cuts, list(cuts[1:]) + [500])]
    ref = [decode_raw_imu(m, float("nan"), 12.5) for m in msgs]
    small_rec, small_usec = np.concatenate([r for r, _ in small]), np.concatenate([u for _, u in small])
    assert small_usec.tolist() == usec.tolist()
    assert all(np.array_equal(small_rec[f], rec[f], equal_nan=True) for f in rec.dtype.names)
    # THEN every value is the same float, the stamps are the messages' own
    assert usec.tolist() == [m.time_usec for m in msgs]
    assert np.array_equal(rec["gyro_rad_s"], np.array([s.gyro_rad_s for s in ref]))
    assert np.array_equal(rec["accel_m_s2"], np.array([s.accel_m_s2 for s in ref]))
    assert rec["imu_id"].tolist() == [s.imu_id for s in ref]
    batch = ImuBatch(rec)
    assert batch.has_mag.tolist() == [s.mag_gauss is not None for s in ref]
    for got, want in zip(batch.samples(), ref):
        assert (got.mag_gauss is None) == (want.mag_gauss is None)
        if want.mag_gauss is not None:
            assert np.array_equal(got.mag_gauss, want.mag_gauss)
        assert np.array_equal(got.gyro_rad_s, want.gyro_rad_s) and got.time_rx_s == want.time_rx_s
        assert got.source == want.source and got.imu_id == want.imu_id
