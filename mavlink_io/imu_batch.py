"""RAW_IMU as one typed numpy array per read: the input side of issue 19 item 3 (batch API).

The per-message path turns every RAW_IMU into a pymavlink message object, then an ImuSample with
three numpy arrays, and the Pipeline takes them one by one. The batch path (LinkConfig.imu_batch,
the daemon's) keeps a read's IMU samples together, in one structured array of :data:`IMU_RECORD`
rows:

    read (the datagrams one poll returned, or a stream chunk)
      -> mavlink_io.frame_scan: unsigned RAW_IMU frames, CRC-checked (fastcrc), set apart as
         payloads; every other byte goes to pymavlink as before, in order
      -> the link: per frame the same checks and counters as the message path (source, sequence,
         link alive, rates), then sample_decoder.stamp_raw_imu (imu id, stream choice, FC time
         through the timebase, its events); rows it does not stamp are dropped as there
      -> :class:`BatchBuilder`: consecutive rows form one :class:`ImuBatch` at their place among
         the read's other items (an event or another message between two samples splits the batch,
         so the order of everything is the message path's); :func:`raw_imu_records` decodes all
         rows of the read with one ``np.frombuffer``
      -> daemon: ``Pipeline.on_imu_batch(batch) -> solutions`` (today a loop over
         :meth:`ImuBatch.samples` calling ``on_imu``; the compiled core's batch API later).

What stays with pymavlink: everything else, any signed frame, and the whole link when it has a
signing key. A missing magnetometer (all three fields 0, as ArduPilot sends without a compass) is
NaN in the row where ImuSample has None; ``has_mag`` says which rows have one. Decoding cost
(tests/test_mavlink_imu_batch.py's frames, CPU time, load 13): pymavlink parse + decode_raw_imu
28 us per RAW_IMU; raw_imu_records 39 us for a batch of 1, 4.5 for 8, 0.8 for 64.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from mavlink_io.decode import MG_TO_M_S2, MGAUSS_TO_GAUSS, MRAD_TO_RAD
from mavlink_io.samples import ImuSample

RAW_IMU_ID = 27
RAW_IMU_CRC_EXTRA = 144
RAW_IMU_WIRE = np.dtype([("time_usec", "<u8"), ("acc", "<i2", (3,)), ("gyro", "<i2", (3,)),
                         ("mag", "<i2", (3,)), ("id", "u1"), ("temperature", "<i2")])
"""RAW_IMU's payload as MAVLink 2 puts it on the wire (fields by size, little endian; 29 bytes; the
sender may cut trailing zero bytes, which :func:`raw_imu_records` restores)."""

IMU_RECORD = np.dtype([("time_fc_s", "<f8"), ("time_rx_s", "<f8"), ("gyro_rad_s", "<f8", (3,)),
                       ("accel_m_s2", "<f8", (3,)), ("mag_gauss", "<f8", (3,)), ("imu_id", "u1")], align=True)
"""One IMU sample, SI units, sensor axes: ImuSample's fields as one row (mag NaN when absent). Laid
out as the C struct {double time_fc_s, time_rx_s, gyro_rad_s[3], accel_m_s2[3], mag_gauss[3];
uint8_t imu_id;} (96 bytes): the first 11 doubles of a row are also a plain float64 block."""
_F8_PER_ROW = IMU_RECORD.itemsize // 8
_WIRE_SIZE = RAW_IMU_WIRE.itemsize
_ACC_AT, _ID_AT = RAW_IMU_WIRE.fields["acc"][1], RAW_IMU_WIRE.fields["id"][1]  # acc, gyro, mag follow each other
_WIRE_SCALE = np.array([MG_TO_M_S2] * 3 + [MRAD_TO_RAD] * 3 + [MGAUSS_TO_GAUSS] * 3)
"""acc (mG), gyro (mrad/s), mag (mgauss) as they follow each other on the wire -> SI."""


_SMALL_BATCH = 8
"""Up to this many rows are decoded in Python (struct, then one np.array): a dozen numpy calls on
tiny arrays cost more than that (CPU at load 10: 18 us vs 114 us for 1 row; 44 vs 132 for 4;
numpy wins from ~12 rows: 184 vs 656 us for 64)."""
_WIRE_UNPACK = struct.Struct("<Q9hB").unpack_from   # time_usec, acc, gyro, mag, id
_array = np.array
_NAN = float("nan")


def raw_imu_records(payloads: list[bytes], time_rx_s: float) -> tuple[np.ndarray, np.ndarray]:
    """RAW_IMU payloads (CRC already checked) -> (IMU_RECORD rows with ``time_fc_s`` NaN, their
    time_usec as uint64 for the timebase to stamp them). mG, mrad/s, mgauss -> m/s^2, rad/s, gauss
    (decode.py's factors: int16 -> float64, times the factor; the same IEEE operations in Python and
    numpy, so both ways give decode_raw_imu's values bit for bit)."""
    padded = [p[:_WIRE_SIZE].ljust(_WIRE_SIZE, b"\0") for p in payloads]
    if len(padded) <= _SMALL_BATCH:
        return _records_small(padded, time_rx_s)
    n = len(padded)
    buf = b"".join(padded)
    raw = np.ndarray((n, 9), dtype="<i2", buffer=buf, offset=_ACC_AT, strides=(_WIRE_SIZE, 2))  # acc, gyro, mag
    si = raw * _WIRE_SCALE
    si[~raw[:, 6:9].any(axis=1), 6:9] = np.nan  # no compass: all three fields 0
    out = np.empty(n, dtype=IMU_RECORD)
    f8 = out.view(np.float64).reshape(n, _F8_PER_ROW)
    f8[:, 0] = np.nan
    f8[:, 1] = time_rx_s
    f8[:, 2:5] = si[:, 3:6]
    f8[:, 5:8] = si[:, 0:3]
    f8[:, 8:11] = si[:, 6:9]
    out["imu_id"] = np.ndarray((n,), dtype="u1", buffer=buf, offset=_ID_AT, strides=(_WIRE_SIZE,))
    return out, np.ndarray((n,), dtype="<u8", buffer=buf, offset=0, strides=(_WIRE_SIZE,)).copy()


def _records_small(padded: list[bytes], time_rx_s: float) -> tuple[np.ndarray, np.ndarray]:
    rows, usec = [], []
    for p in padded:
        t, a0, a1, a2, g0, g1, g2, m0, m1, m2, imu_id = _WIRE_UNPACK(p)
        mag = ((_NAN, _NAN, _NAN) if m0 == 0 and m1 == 0 and m2 == 0
               else (m0 * MGAUSS_TO_GAUSS, m1 * MGAUSS_TO_GAUSS, m2 * MGAUSS_TO_GAUSS))
        rows.append((_NAN, time_rx_s, (g0 * MRAD_TO_RAD, g1 * MRAD_TO_RAD, g2 * MRAD_TO_RAD),
                     (a0 * MG_TO_M_S2, a1 * MG_TO_M_S2, a2 * MG_TO_M_S2), mag, imu_id))
        usec.append(t)
    return np.array(rows, dtype=IMU_RECORD), np.array(usec, dtype=np.uint64)


def raw_imu_sample(payload: bytes, time_fc_s: float, time_rx_s: float) -> ImuSample:
    """One RAW_IMU payload (CRC already checked, as frame_scan takes it) -> the ImuSample the message
    path hands on: decode.decode_raw_imu's values bit for bit (the same int -> float64 array times the
    same factor), without a pymavlink message object. A cut payload's missing bytes are zeros."""
    _t, a0, a1, a2, g0, g1, g2, m0, m1, m2, imu_id = _WIRE_UNPACK(
        payload if len(payload) == _WIRE_SIZE else payload[:_WIRE_SIZE].ljust(_WIRE_SIZE, b"\0"))
    # float(int16) * factor in Python is the float64 product numpy forms (int -> float64 exact): the same
    # bits with one array per vector instead of an int array, a float copy and a product (17 -> 6.5 us)
    mag = None if m0 == 0 and m1 == 0 and m2 == 0 else \
        _array((m0 * MGAUSS_TO_GAUSS, m1 * MGAUSS_TO_GAUSS, m2 * MGAUSS_TO_GAUSS))
    return ImuSample(time_fc_s, time_rx_s, _array((g0 * MRAD_TO_RAD, g1 * MRAD_TO_RAD, g2 * MRAD_TO_RAD)),
                     _array((a0 * MG_TO_M_S2, a1 * MG_TO_M_S2, a2 * MG_TO_M_S2)), mag, "RAW_IMU", imu_id)


@dataclass(frozen=True, slots=True)
class ImuBatch:
    """The IMU samples of one read, in FC time order, each row stamped by the timebase."""
    records: np.ndarray
    """IMU_RECORD rows."""
    source: str = "RAW_IMU"

    def __len__(self) -> int:
        return len(self.records)

    @property
    def has_mag(self) -> np.ndarray:
        return np.isfinite(self.records["mag_gauss"][:, 0])

    def samples(self) -> list[ImuSample]:
        """The same samples as ImuSample objects (the per-sample Pipeline.on_imu until its batch
        API exists): each its own arrays, as the message path gives."""
        src, arr = self.source, np.array
        return [ImuSample(t_fc, t_rx, arr(g), arr(a), arr(m) if m[0] == m[0] else None, src, imu_id)  # NaN: no compass
                for t_fc, t_rx, g, a, m, imu_id in self.records.tolist()]


class _Slot:
    """A batch's place in the read's item list while its rows are collected."""
    __slots__ = ("start", "end")

    def __init__(self, start: int):
        self.start, self.end = start, start + 1


class BatchBuilder:
    """The stamped RAW_IMU rows of one read, and where each run of them goes among its items.

    ``add`` puts a placeholder in ``items`` for a new run (or extends the run that is the last
    item); ``finish`` decodes every row of the read at once and replaces each placeholder by its
    ImuBatch."""

    def __init__(self):
        self._payloads: list[bytes] = []
        self._times_fc_s: list[float] = []
        self._slot: _Slot | None = None

    def add(self, payload: bytes, time_fc_s: float, items: list) -> None:
        slot = self._slot
        if slot is not None and items and items[-1] is slot:
            slot.end += 1
        else:
            self._slot = _Slot(len(self._payloads))
            items.append(self._slot)
        self._payloads.append(payload)
        self._times_fc_s.append(time_fc_s)

    def finish(self, items: list, time_rx_s: float) -> None:
        if not self._payloads:
            return
        records, _ = raw_imu_records(self._payloads, time_rx_s)
        records["time_fc_s"] = self._times_fc_s
        for i, it in enumerate(items):
            if type(it) is _Slot:
                items[i] = ImuBatch(records[it.start:it.end])
        self._payloads, self._times_fc_s, self._slot = [], [], None
