"""CPU per RAW_IMU on the link's receive path: the message path against the batch path (issue 19 item 3).

    python bench/imu_batch_cost.py [--samples 4000] [--repeat 3] [--json PATH] [--quick]

A MavlinkLink on an in-memory transport reads RAW_IMU frames (after the FC's HEARTBEAT), the way
the daemon's loop does (``poll``), with 1, 4, 8 or 32 frames per read, each frame its own datagram
or the read's frames packed in one; what the daemon then hands the Pipeline is included
(``ImuBatch.samples()`` on the batch path, the ImuSample itself on the message path). CPU time
(process), best of ``--repeat``; the load is printed beside it (a shared machine inflates every
figure, not their ratio much).

- ``message_us_per_imu``: LinkConfig.imu_batch off (the default): frame_scan sets the RAW_IMU frames
  apart (fastcrc) and each becomes its ImuSample without pymavlink (imu_batch.raw_imu_sample);
- ``pymavlink_us_per_imu``: the message path as with a signing key: pymavlink parses and decodes
  every frame (what the message path did until session 10);
- ``batch_us_per_imu``: imu_batch on: frame_scan sets the RAW_IMU frames apart, one decode per read.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]


def _frames(n: int) -> tuple[bytes, list[bytes]]:
    from pymavlink.dialects.v20 import ardupilotmega as mav
    fc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    hb = mav.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3).pack(fc)
    out = []
    for k in range(n):
        fc.seq = k % 256
        out.append(mav.MAVLink_raw_imu_message(1_000_000 + 2500 * k, 1, 2, -1000, 3, 4, 5, 6, 7, 8, 0, 0).pack(fc))
    return hb, out


def cpu_us_per_imu(batch: bool, per_read: int, packed: bool, hb: bytes, frames: list[bytes],
                   pymavlink: bool = False) -> float:
    from mavlink_io.imu_batch import ImuBatch
    from mavlink_io.link import LinkConfig, MavlinkLink
    from mavlink_io.samples import ImuSample
    from mem_transport import MemTransport
    t = [0.0]
    tr = MemTransport()
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", imu_batch=batch), clock=lambda: t[0], transport=tr)
    if pymavlink:
        link._parser.split_imu = False
    tr.inbox.append(hb)
    link.poll(0.0)
    n = 0
    c0 = time.process_time()
    for i in range(0, len(frames), per_read):
        group = frames[i:i + per_read]
        tr.inbox.extend([b"".join(group)] if packed else group)
        t[0] += 0.0025 * per_read
        for it in link.poll(0.0):
            if isinstance(it, ImuBatch):
                n += len(it.samples())
            elif isinstance(it, ImuSample):
                n += 1
    cpu = time.process_time() - c0
    if n != len(frames):
        raise RuntimeError(f"{n} of {len(frames)} samples came out")
    return cpu / n * 1e6


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=4000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="1000 samples")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    hb, frames = _frames(1000 if a.quick else a.samples)
    rows = []
    for per_read in (1, 4, 8, 32):
        for packed in ((False,) if per_read == 1 else (False, True)):
            m, pm, b = (min(cpu_us_per_imu(batch, per_read, packed, hb, frames, pym) for _ in range(a.repeat))
                        for batch, pym in ((False, False), (False, True), (True, False)))
            load = os.getloadavg()[0]
            rows.append({"frames_per_read": per_read, "packed_in_one_datagram": packed, "message_us_per_imu": m,
                         "pymavlink_us_per_imu": pm, "batch_us_per_imu": b, "load_avg_1min": load})
            print(f"{per_read:2d} frames per read{' (one datagram)' if packed else '':15s}: message path "
                  f"{m:6.1f} us (through pymavlink {pm:6.1f}), batch path {b:6.1f} us CPU per RAW_IMU "
                  f"(load {load:.1f})")
    if a.json:
        Path(a.json).write_text(json.dumps({"samples": len(frames), "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
