"""RAW_IMU as one typed numpy array per read: the input side of issue 19 item 3 (batch API).

Today every RAW_IMU becomes a pymavlink message object, then an ImuSample with three numpy arrays,
then ``dataclasses.replace`` for its FC time, and the Pipeline takes them one by one. The batch path
keeps a read's IMU samples together, in one structured array of :data:`IMU_RECORD` rows:

    read (one datagram, or what a stream transport returned)
      -> framing: CRC-checked frames; unsigned RAW_IMU (id 27) frames are set apart as payloads
      -> :func:`raw_imu_records` (one ``np.frombuffer`` for all of them; SI units)
      -> sample_decoder: FC time per row through the timebase (same rules as ImuSample's), the rows
         the timebase drops removed
      -> the link yields one :class:`ImuBatch` per read, in order with the other items
      -> daemon: ``Pipeline.on_imu_batch(batch) -> solutions`` (to be written by the Pipeline's
         owner over the compiled core's batch API; until then :meth:`ImuBatch.samples` feeds
         ``Pipeline.on_imu`` one sample at a time, the same values as the per-sample path).

What stays with pymavlink: everything else, and any signed frame (the security module verifies
it first). A missing magnetometer (all three fields 0, as ArduPilot sends without a compass) is NaN
in the row where ImuSample has None; ``has_mag`` says which rows have one.

Only the decoding is here and tested (equal to :func:`mavlink_io.decode.decode_raw_imu`); the link
does not use it yet. Its cost (tests/test_mavlink_imu_batch.py's frames, CPU time, load 13):
pymavlink parse + decode_raw_imu 28 us per RAW_IMU; raw_imu_records 39 us for a batch of 1, 4.5 for
8, 0.8 for 64 (frame scan and CRC not included: fastcrc's share is to be added). So it pays only
where a read holds several samples (400 Hz, a loop working off a backlog), not one 50 Hz datagram.
"""
from __future__ import annotations

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
                       ("accel_m_s2", "<f8", (3,)), ("mag_gauss", "<f8", (3,)), ("imu_id", "u1")])
"""One IMU sample, SI units, sensor axes: ImuSample's fields as one row (mag NaN when absent)."""


def raw_imu_records(payloads: list[bytes], time_rx_s: float) -> tuple[np.ndarray, np.ndarray]:
    """RAW_IMU payloads (CRC already checked) -> (IMU_RECORD rows with ``time_fc_s`` NaN, their
    time_usec as uint64 for the timebase to stamp them). mG, mrad/s, mgauss -> m/s^2, rad/s, gauss
    (decode.py's factors)."""
    n = len(payloads)
    size = RAW_IMU_WIRE.itemsize
    wire = np.frombuffer(b"".join(p[:size].ljust(size, b"\0") for p in payloads), dtype=RAW_IMU_WIRE, count=n)
    out = np.empty(n, dtype=IMU_RECORD)
    out["time_fc_s"] = np.nan
    out["time_rx_s"] = time_rx_s
    out["accel_m_s2"] = wire["acc"] * MG_TO_M_S2
    out["gyro_rad_s"] = wire["gyro"] * MRAD_TO_RAD
    mag = wire["mag"] * MGAUSS_TO_GAUSS
    mag[np.all(wire["mag"] == 0, axis=1)] = np.nan  # no compass: all three fields 0
    out["mag_gauss"] = mag
    out["imu_id"] = wire["id"]
    return out, wire["time_usec"].copy()


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
        API exists)."""
        out = []
        for r in self.records:
            mag = r["mag_gauss"]
            out.append(ImuSample(float(r["time_fc_s"]), float(r["time_rx_s"]), r["gyro_rad_s"].copy(),
                                 r["accel_m_s2"].copy(), mag.copy() if np.isfinite(mag[0]) else None,
                                 self.source, int(r["imu_id"])))
        return out
