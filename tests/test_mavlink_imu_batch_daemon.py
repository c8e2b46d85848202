"""The batch path against the message path, through the whole daemon (issue 19 item 3).

GIVEN one recorded stream from the bundled simulator (RAW_IMU at 200 Hz, pressure, attitude, status;
a launch; an FC reboot; bad frames mixed in: a RAW_IMU with a broken CRC, garbage, a RAW_IMU from
another component, a repeated RAW_IMU, a frame cut short), fed in memory on the recording's clock to
daemons with LinkConfig.imu_batch off (the message path: one ImuSample per RAW_IMU) and on:
- one frame per datagram: the message path reads one datagram at a time, the batch path all the
  datagrams of 20 ms in one read (both at the group's time, so that the receive times are equal);
- packed: each 20 ms of frames in one datagram (the cut frame then swallows frames after it, as a
  damaged frame with a lying length does), one read each, for both paths.
THEN the Pipeline's solutions (every field), the daemon's events, the link's receive counters and
the Pipeline's counters are identical, and the batch runs did take the batch path. (Our MAVLink
outputs are due once per batch, with the attitude of its newest sample, so what is sent may differ.)
"""
from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.imu_batch import ImuBatch
from mavlink_io.link import MavlinkLink
from mem_transport import MemTransport

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import scenario_site  # noqa: E402

SCENARIO = "inclined_rail"
FLIGHT_S = 8.0
REBOOT_AT_S = 7.0
RATES_HZ = {27: 200.0, 29: 25.0, 30: 25.0, 1: 2.0, 193: 2.0}  # RAW_IMU, SCALED_PRESSURE, ATTITUDE, SYS_STATUS, EKF
READ_S = 0.02


class _Recorder:
    def __init__(self, sysid: int, compid: int):
        self.frames: list[tuple[float, bytes]] = []
        self.t = 0.0
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=compid)

    def write(self, buf):
        self.frames.append((self.t, bytes(buf)))


def _record() -> list[tuple[float, bytes]]:
    from sim.autopilot import Autopilot
    ap = Autopilot(SCENARIO, "udpout:127.0.0.1:9", personality="ardupilot", seed=3,
                   overrides={"launcher": {"rest_s": 4.0}, "faults": {"reboot_at_s": REBOOT_AT_S,
                                                                     "reboot_silence_s": 0.3}})
    rec = ap.conn = _Recorder(ap.sysid, ap.compid)

    def streams():
        for mid, hz in RATES_HZ.items():
            ap.set_interval(mid, 1e6 / hz)
    streams()
    rebooted = False
    while ap.t < FLIGHT_S:
        t_next = min(s.next_s for s in ap.streams.values())
        if ap.reboot_at is not None and ap.t < ap.reboot_at <= t_next:
            t_next = ap.reboot_at
        ap.t = rec.t = t_next
        if ap.reboot_at is not None and ap.t >= ap.reboot_at:
            ap.reboot_at, rebooted = None, True
            ap._reboot()
            continue
        if rebooted and ap.t >= ap.silent_until:  # the link would ask again; the recording does
            rebooted = False
            streams()
        for mid, st in list(ap.streams.items()):
            if st.next_s <= ap.t + 1e-9 and ap.streams.get(mid) is st:
                ap._send(ap._build(mid, st))
                st.next_s += st.interval_s
    return _with_bad_frames(rec.frames, ap.sysid)


def _with_bad_frames(frames: list[tuple[float, bytes]], sysid: int) -> list[tuple[float, bytes]]:
    """Bad input every reader meets, at fixed places after the FC's first HEARTBEAT (t > 1 s)."""
    imu = [i for i, (t, f) in enumerate(frames) if f[7] == 27 and t > 1.0]
    out = list(frames)
    i_crc, i_foreign, i_repeat, i_garbage, i_cut = imu[100], imu[300], imu[500], imu[700], imu[900]
    t, f = frames[i_crc]
    out[i_crc] = (t, f[:12] + bytes([f[12] ^ 0x40]) + f[13:])          # broken CRC
    other = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=99)
    t, f = frames[i_foreign]
    out.insert(i_foreign, (t, other.raw_imu_encode(int(t * 1e6), 1, 2, 3, 4, 5, 6, 7, 8, 9).pack(other)))
    out.insert(i_repeat + 1, frames[i_repeat])                           # the same frame again
    out.insert(i_garbage + 1, (frames[i_garbage][0], b"\x00\x13garbage\x07"))
    t, f = frames[i_cut]
    out.insert(i_cut + 1, (t, f[:20]))                                   # a frame cut short
    return out


def _reads(frames, packed: bool) -> list[tuple[float, list[bytes]]]:
    """Group the frames into reads of READ_S; each read at the time of its last frame."""
    reads, cur, t_end = [], [], None
    for t, f in frames:
        if t_end is not None and t > t_end:
            reads.append((cur_t, [b"".join(cur)] if packed else cur))
            cur, t_end = [], None
        if t_end is None:
            t_end = math.floor(t / READ_S) * READ_S + READ_S
        cur.append(f)
        cur_t = t
    reads.append((cur_t, [b"".join(cur)] if packed else cur))
    return reads


def _run(tmp_path: Path, name: str, reads, batch: bool, one_per_read: bool = False, pymavlink_only: bool = False):
    from service.config import validate
    from service.daemon import Daemon
    over = {k: dict(v) for k, v in scenario_site(SCENARIO).items()}
    over.update({"zenoh": {"enabled": False}, "service": {"state_dir": str(tmp_path / name)},
                 "azimuth": {"solve_in_background": False}})
    clock = [0.0]
    d = Daemon(validate(over), clock=lambda: clock[0])
    tr = MemTransport(datagram=True)
    d.link = MavlinkLink(dataclasses.replace(d.link_cfg, imu_batch=batch), clock=lambda: clock[0], transport=tr)
    if pymavlink_only:   # every frame parsed and decoded by pymavlink (as a link with a signing key)
        d.link._parser.split_imu = False
    events, solutions, kinds = [], [], {"batches": 0, "batch_rows": 0, "samples": 0}
    d._event = lambda kind, detail: events.append((kind, detail))
    publish = d.publish
    d.publish = lambda sol: (solutions.append(sol), publish(sol))
    for t, datagrams in reads:
        clock[0] = t
        for read in ([[dg] for dg in datagrams] if one_per_read else [datagrams]):
            tr.inbox.extend(read)
            for item in d.link.poll(0.0):
                if isinstance(item, ImuBatch):
                    kinds["batches"] += 1
                    kinds["batch_rows"] += len(item)
                elif type(item).__name__ == "ImuSample":
                    kinds["samples"] += 1
                d.dispatch(item)
        d._publish_due(t)
    stats = d.link.stats.as_dict()
    counters = dataclasses.asdict(d.pipeline.counters)
    d.pipeline.solver.close()
    return solutions, events, stats, counters, kinds


def _same_solution(a, b) -> bool:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True):
                return False
        elif isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y):
            continue
        elif x != y:
            return False
    return True


@pytest.fixture(scope="module")
def recording():
    return _record()


def test_batched_reads_give_the_message_paths_solutions_events_and_counts(recording, tmp_path):
    per_frame, packed = _reads(recording, packed=False), _reads(recording, packed=True)
    pairs = {"datagram per frame": (_run(tmp_path, "m1", per_frame, batch=False, one_per_read=True),
                                    _run(tmp_path, "b1", per_frame, batch=True)),
             "packed": (_run(tmp_path, "m2", packed, batch=False), _run(tmp_path, "b2", packed, batch=True))}
    for name, (message, batch) in pairs.items():
        sols0, events0, stats0, counters0, kinds0 = message
        # the recording exercised what it should: a flight's solutions, the reboot, every bad frame
        assert len(sols0) > 100 and kinds0["batches"] == 0 and kinds0["samples"] > 1500, name
        assert any(k == "fc_reboot" for k, _ in events0) and any(k == "phase" for k, _ in events0), name
        assert stats0["crc_errors"] >= 1 and stats0["framing_errors"] >= 1, name
        assert stats0["foreign_messages"] >= 1 and stats0["stale_time_drops"] >= 1, name
        sols, events, stats, counters, kinds = batch
        # the batch path was taken: every sample came in a batch, several to a batch
        assert kinds["samples"] == 0 and kinds["batch_rows"] == kinds0["samples"], name
        assert kinds["batches"] < kinds["batch_rows"] / 2, name
        # and nothing differs
        assert len(sols) == len(sols0), name
        assert all(_same_solution(a, b) for a, b in zip(sols, sols0)), name
        assert events == events0, name
        assert counters == counters0, name
        differ = {k: (stats[k], stats0[k]) for k in stats0 if stats[k] != stats0[k]
                  and k not in ("messages_sent", "send_errors")}
        assert differ == {}, name


def _link_items(reads, split: bool) -> list:
    """Everything a message-path link hands on for the reads (a frame per datagram, one read each)."""
    from mavlink_io.link import LinkConfig
    clock = [0.0]
    tr = MemTransport(datagram=True)
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:14550"), clock=lambda: clock[0], transport=tr)
    link._parser.split_imu = split
    items = []
    for t, datagrams in reads:
        clock[0] = t
        for dg in datagrams:
            tr.inbox.append(dg)
            items += link.poll(0.0)
    return items, link.stats.as_dict()


def _same_item(a, b) -> bool:
    if type(a) is not type(b):
        return False
    if not dataclasses.is_dataclass(a):
        return a == b
    return _same_solution(a, b) and all(
        (getattr(a, f.name) is None) == (getattr(b, f.name) is None) for f in dataclasses.fields(a))


def test_the_message_path_decodes_raw_imu_without_pymavlink_as_pymavlink_does(recording, tmp_path):
    """GIVEN the recording above, a frame per datagram and packed, WHEN the message path (no signing key)
    sets RAW_IMU frames apart (frame_scan, fastcrc) and builds each ImuSample itself
    (imu_batch.raw_imu_sample) and WHEN pymavlink parses and decodes every frame, THEN the link hands on
    the same items (every ImuSample field for field, bit for bit; a missing compass None) with the same
    receive counters, and the daemons make the same solutions, events and counts."""
    from mavlink_io import frame_scan
    from mavlink_io.samples import ImuSample
    assert frame_scan.AVAILABLE   # fastcrc is a dependency
    per_frame = _reads(recording, packed=False)
    fast, fast_stats = _link_items(per_frame, split=True)
    slow, slow_stats = _link_items(per_frame, split=False)
    n_imu = sum(type(i) is ImuSample for i in slow)
    assert n_imu > 1500 and slow_stats["crc_errors"] >= 1 and slow_stats["framing_errors"] >= 1
    assert len(fast) == len(slow) and all(_same_item(a, b) for a, b in zip(fast, slow))
    assert fast_stats == slow_stats
    for name, reads, one in (("datagram per frame", per_frame, True),
                             ("packed", _reads(recording, packed=True), False)):
        sols0, events0, stats0, counters0, kinds0 = _run(tmp_path, f"p{one}", reads, batch=False, one_per_read=one,
                                                         pymavlink_only=True)
        sols, events, stats, counters, kinds = _run(tmp_path, f"f{one}", reads, batch=False, one_per_read=one)
        assert kinds == kinds0 and kinds["samples"] > 1500, name
        assert len(sols) == len(sols0) > 100 and all(_same_solution(a, b) for a, b in zip(sols, sols0)), name
        assert events == events0 and counters == counters0, name
        assert {k: (stats[k], stats0[k]) for k in stats0 if stats[k] != stats0[k]} == {}, name
