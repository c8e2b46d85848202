"""The compiled frame scan (core/mavlink_frames.hpp, core/bindings_link.cpp, handed to the link by
service/link_core.py) equals mavlink_io.frame_scan.split_raw_imu, the reference: the same segments and
RawImuFrames on recorded flights (the real ArduCopter tlog, its RAW_IMU re-framed as MAVLink 2, and a
simulator recording) and on a fault corpus (corrupt, truncated, cut, wrong-CRC, signed, MAVLink 1,
garbage); and a MavlinkLink with either gives the same items (samples bit for bit, events), counters and
rates, per datagram and as a byte stream split anywhere, with sequence gaps and FC time jumps.
``test_comparison_catches_a_mutant`` shows the comparison fails for a scan that differs in one field."""
from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io import frame_scan
from mavlink_io.frame_scan import RawImuFrame
from mavlink_io.link import LinkConfig, MavlinkLink
from mavlink_io.tlog import read_tlog
from mavlink_io.transport import NullTransport
from service import link_core

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")
TLOG = DATA / "arducopter-flight.tlog"

CORE_SCAN = link_core.frame_scan({})
needs_core = pytest.mark.skipif(CORE_SCAN is None, reason="compiled core without split_raw_imu")


# --- recordings and the fault corpus --------------------------------------------------------------

def _tlog_frames() -> list[tuple[float, bytes]]:
    if not TLOG.is_file():
        pytest.skip(f"{TLOG} not found (the real logs live in ../shared/data)")
    return list(read_tlog(TLOG))


def _tlog_as_v2(frames: list[tuple[float, bytes]]) -> list[tuple[float, bytes]]:
    """The tlog's frames with every RAW_IMU and HEARTBEAT re-framed as MAVLink 2 (same sender, sequence and
    fields: what a MAVLink 2 FC sends; pymavlink cuts the payload's trailing zeros), the rest as recorded."""
    rx = mavlink2.MAVLink(None, srcSystem=0, srcComponent=0)
    rx.robust_parsing = True
    out = []
    for t, f in frames:
        msg = rx.parse_char(f)
        if msg is not None and msg.get_type() in ("RAW_IMU", "HEARTBEAT"):
            mav = mavlink2.MAVLink(None, srcSystem=msg.get_srcSystem(), srcComponent=msg.get_srcComponent())
            mav.seq = msg.get_seq()
            f = msg.pack(mav)
        out.append((t, f))
    return out


def _sim_frames() -> list[tuple[float, bytes]]:
    """The bundled simulator (ArduPilot personality) at the daemon's 400 Hz streams: one frame a datagram."""
    import sys
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        from daemon_loop_cost import record
    finally:
        sys.path.remove(str(ROOT / "bench"))
    return record(6.0)[:4000]


def _fc(seq0: int = 0):
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.seq = seq0
    return mav


def _pack(msg, mav, **kw) -> bytes:
    frame = msg.pack(mav, **kw)
    mav.seq = (mav.seq + 1) % 256   # as MAVLink.send does
    return frame


def _raw_imu(mav, t_us: int, imu_id: int = 0, mag=(300, -20, 400)):
    return _pack(mavlink2.MAVLink_raw_imu_message(t_us, 10, -20, -1000, 1, 2, 3, *mag, imu_id, 2500), mav)


def _fault_corpus() -> list[tuple[float, bytes]]:
    """(rx time s, datagram): a good stream, then each fault the link counts or reports."""
    fc, gcs = _fc(), mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    out: list[tuple[float, bytes]] = []
    rx = 100.0
    t_us = 5_000_000

    def add(data: bytes, dt_s: float = 0.0025):
        nonlocal rx
        out.append((rx, data))
        rx += dt_s

    add(_pack(mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3), fc))
    for k in range(40):
        t_us += 2500
        add(_raw_imu(fc, t_us))
    good = _raw_imu(fc, t_us + 2500)
    t_us += 2500
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0x55
    add(bytes(bad_crc))                                     # wrong CRC
    corrupt = bytearray(_raw_imu(fc, t_us + 2500))
    t_us += 2500
    corrupt[14] ^= 0x01                                     # a payload bit flipped: CRC fails
    add(bytes(corrupt))
    add(_raw_imu(fc, t_us + 2500)[:20])                    # truncated: cut by the end of the datagram
    t_us += 2500
    add(b"\x00\x13garbage\x55" + _raw_imu(fc, t_us + 2500))  # a bad prefix, then a good frame
    t_us += 2500
    add(_raw_imu(fc, t_us + 2500, mag=(0, 0, 0)))            # no compass: trailing fields 0, payload cut shorter
    t_us += 2500
    signer = _fc(fc.seq)
    signer.signing.secret_key = bytes(range(32))
    signer.signing.sign_outgoing = True
    signer.signing.timestamp = 1
    add(_raw_imu(signer, t_us + 2500))                      # signed: left to pymavlink
    fc.seq = signer.seq
    t_us += 2500
    v1 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    v1.seq = fc.seq
    add(_pack(mavlink2.MAVLink_raw_imu_message(t_us + 2500, 1, 2, -1000, 0, 0, 0, 1, 1, 1, 0, 0), v1,
              force_mavlink1=True))
    fc.seq = v1.seq
    t_us += 2500
    add(_raw_imu(gcs, t_us + 2500))                         # another component: foreign
    add(_raw_imu(mavlink2.MAVLink(None, srcSystem=1, srcComponent=191), t_us + 2500))  # our own echo
    add(_raw_imu(fc, t_us + 2500, imu_id=1))                # another IMU instance
    t_us += 2500
    fc.seq = (fc.seq + 7) % 256                             # sequence gap: 7 lost
    add(_raw_imu(fc, t_us + 2500))
    t_us += 2500
    add(_raw_imu(fc, t_us - 1000))                          # FC time back a little: stale
    add(_raw_imu(fc, t_us + 800_000))                       # a 0.8 s gap in FC time (imu_gap_s 0.5)
    t_us += 800_000
    multi = b"".join(_raw_imu(fc, t_us + 2500 * (k + 1)) for k in range(5))
    t_us += 12_500
    add(multi[:-3] + _pack(mavlink2.MAVLink_attitude_message(7000, 0.1, 0.2, 0.3, 0, 0, 0), fc))  # a cut frame inside
    add(b"\xfd\x1d\x00\x00")                                 # a header alone
    add(b"\xfd\x1d\x02\x00" + bytes(40))                     # an unknown incompatibility flag
    whole = _raw_imu(fc, t_us + 2500)
    t_us += 2500
    add(whole[:9])                                          # one frame split across two datagrams: from here
    add(whole[9:])                                          # on the link parses UDP as a byte stream
    add(_raw_imu(fc, t_us + 2500)[:30])                     # and a cut frame swallows the next datagram's start
    t_us += 2500
    for k in range(3):
        t_us += 2500
        add(_raw_imu(fc, t_us))
    t_us = 1_000_000                                        # the FC rebooted: its clock restarted
    for k in range(10):
        t_us += 2500
        add(_raw_imu(fc, t_us), 0.05 if k == 0 else 0.0025)
    return out


# --- comparison -----------------------------------------------------------------------------------

def _norm(x):
    """A value compared exactly: floats by their bits, arrays by shape and bits, dataclasses by fields."""
    if isinstance(x, float):
        return ("f", x.hex())
    if isinstance(x, np.ndarray):
        if x.dtype.names:   # structured rows: field by field (the padding bytes are not values)
            return ("a", x.shape, tuple((n, _norm(np.ascontiguousarray(x[n]))) for n in x.dtype.names))
        return ("a", x.shape, x.dtype.str, x.tobytes())
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return (type(x).__name__,) + tuple(_norm(getattr(x, f.name)) for f in dataclasses.fields(x))
    if isinstance(x, (list, tuple)):
        return (type(x).__name__,) + tuple(_norm(v) for v in x)
    if isinstance(x, dict):
        return tuple(sorted((k, _norm(v)) for k, v in x.items()))
    if isinstance(x, set):
        return tuple(sorted(x))
    return x


def _as_stream(datagrams, seed: int) -> list[tuple[float, bytes]]:
    """The datagrams' bytes as one stream (serial, TCP) cut at random offsets; each read's time is that
    of the datagram its first byte came from."""
    blob = b"".join(d for _t, d in datagrams)
    times = [tt for tt, d in datagrams for _ in range(len(d))]
    cuts = [0] + sorted(random.Random(seed).sample(range(1, len(blob)), len(blob) // 40)) + [len(blob)]
    return [(times[a], blob[a:b]) for a, b in zip(cuts, cuts[1:])]


def _link_run(datagrams, scan, datagram: bool = True, imu_batch: bool = False):
    """Items, counters and rates of a MavlinkLink fed ``datagrams`` (one feed each, as datagrams or as reads
    of a byte stream) with the frame scan ``scan`` (None: Python)."""
    t = [0.0]
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", imu_batch=imu_batch), clock=lambda: t[0],
                       transport=NullTransport(None), frame_scan=scan)
    items = []
    for rx, data in datagrams:
        t[0] = rx
        items.extend(link.feed(data, rx, datagram=datagram))
        items.extend(link.poll(0.0))
    return [_norm(i) for i in items], _norm(link.stats.as_dict()), link


def _assert_same_links(datagrams, scan, **kw):
    ref_items, ref_stats, ref = _link_run(datagrams, None, **kw)
    items, stats, link = _link_run(datagrams, scan, **kw)
    assert link._parser.scan is scan and ref._parser.scan is frame_scan.split_raw_imu
    assert len(items) == len(ref_items)
    assert items == ref_items
    assert stats == ref_stats
    return ref_items, ref_stats


def _scan_equal(scan, data: bytes) -> bool:
    a, b = scan(data), frame_scan.split_raw_imu(data)
    return a == b and [type(x) for x in a] == [type(x) for x in b]


# --- tests ----------------------------------------------------------------------------------------

@needs_core
def test_scan_equals_python_on_the_real_tlog_and_a_simulator_recording():
    # GIVEN the real ArduCopter tlog (MAVLink 1), the same with RAW_IMU and HEARTBEAT as MAVLink 2, and the simulator
    tlog = _tlog_frames()
    sources = {"tlog": tlog, "tlog_v2": _tlog_as_v2(tlog), "sim": _sim_frames()}
    rnd = random.Random(19)
    for name, frames in sources.items():
        # WHEN each frame, and the stream cut into random chunks, is scanned by both
        taken = sum(type(p) is RawImuFrame for _t, f in frames for p in frame_scan.split_raw_imu(f))
        blob = b"".join(f for _t, f in frames)
        pos, chunks = 0, []
        while pos < len(blob):
            k = rnd.randrange(1, 300)
            chunks.append(blob[pos:pos + k])
            pos += k
        # THEN the segments and frames are the same, in order
        assert all(_scan_equal(CORE_SCAN, f) for _t, f in frames), name
        assert all(_scan_equal(CORE_SCAN, c) for c in chunks), name
        assert _scan_equal(CORE_SCAN, blob), name
        # and the recordings do exercise the taken path (the MAVLink 1 tlog: none taken)
        assert (taken > 1000) == (name != "tlog"), (name, taken)


@needs_core
def test_scan_equals_python_on_the_fault_corpus_and_mutated_bytes():
    # GIVEN the fault corpus and the simulator's frames with random bytes changed, cut and joined
    corpus = [d for _t, d in _fault_corpus()]
    assert all(_scan_equal(CORE_SCAN, d) for d in corpus)
    assert _scan_equal(CORE_SCAN, b"".join(corpus))
    sim = [f for _t, f in _sim_frames()[:600]]
    rnd = random.Random(7)
    for i in range(3000):
        chunk = bytearray(b"".join(sim[i % 550:i % 550 + rnd.randrange(1, 6)]))
        for _ in range(rnd.randrange(0, 3)):
            chunk[rnd.randrange(len(chunk))] = rnd.choice((0xFD, 0xFE, 0x00, 0x01, rnd.randrange(256)))
        if rnd.random() < 0.3:
            chunk = chunk[rnd.randrange(len(chunk)):]
        if rnd.random() < 0.3:
            chunk = chunk[:rnd.randrange(len(chunk) + 1)]
        # WHEN scanned by both THEN the same (bytearray input: the core copies it to bytes first)
        assert _scan_equal(CORE_SCAN, bytes(chunk)), bytes(chunk).hex()
        assert CORE_SCAN(bytearray(chunk)) == frame_scan.split_raw_imu(bytes(chunk))
    assert CORE_SCAN(b"") == [] == frame_scan.split_raw_imu(b"")


@needs_core
@pytest.mark.parametrize("imu_batch", [False, True])
def test_link_with_the_core_scan_equals_the_python_link_on_the_fault_corpus(imu_batch):
    # GIVEN the fault corpus as datagrams
    corpus = _fault_corpus()
    # WHEN a link with the core scan and one with the Python scan are fed it
    items, stats = _assert_same_links(corpus, CORE_SCAN, imu_batch=imu_batch)
    # THEN (asserted inside) the same items and counters; and the corpus did reach every fault it names
    s = dict(stats)
    assert s["crc_errors"] >= 2 and s["framing_errors"] >= 1 and s["seq_lost"] >= 7 and s["foreign_messages"] >= 1
    assert s["own_echoes"] == 1
    assert s["stale_time_drops"] >= 1 and s["time_gaps"] >= 1 and s["fc_reboots"] == 1
    assert s["datagram_resets"] >= 1 and s["udp_split_frames_seen"] == 1
    kinds = [i[1] for i in items if i[0] == "LinkEvent"]
    assert "fc_reboot" in kinds and "time_gap" in kinds and "autopilot_detected" in kinds


@needs_core
def test_link_with_the_core_scan_equals_the_python_link_as_a_byte_stream():
    # GIVEN the fault corpus and the v2 tlog as one byte stream (serial, TCP) cut at random offsets
    for datagrams in (_fault_corpus(), _tlog_as_v2(_tlog_frames())[:6000]):
        reads = _as_stream(datagrams, 3)
        # WHEN both links read it THEN the same items and counters
        items, _stats = _assert_same_links(reads, CORE_SCAN, datagram=False)
        assert sum(1 for i in items if i[0] == "ImuSample") > 20


@needs_core
def test_link_with_the_core_scan_equals_the_python_link_on_recordings():
    # GIVEN the simulator's 400 Hz frames and the real tlog with RAW_IMU as MAVLink 2, one frame a datagram
    for datagrams in (_sim_frames(), _tlog_as_v2(_tlog_frames())[:8000]):
        # WHEN both links read them THEN the same samples, events and counters
        items, stats = _assert_same_links(datagrams, CORE_SCAN)
        assert sum(1 for i in items if i[0] == "ImuSample") > 250


@needs_core
def test_comparison_catches_a_mutant():
    # GIVEN scans that differ from the reference in one thing each (a sequence number, a CRC not checked)
    def seq_off(data):
        return [RawImuFrame(*p[:2], (p.seq + 1) % 256, *p[3:]) if type(p) is RawImuFrame and p.seq == 10 else p
                for p in CORE_SCAN(data)]

    def no_crc(data):
        out = CORE_SCAN(data)
        if type(out[0]) is bytes and len(data) > 12 and data[0] == 0xFD and data[7] == 27 and data[2] == 0:
            p = data[10:10 + data[1]]
            return [RawImuFrame(data[5], data[6], data[4], p, int.from_bytes(p[:8], "little"),
                                p[26] if len(p) > 26 else 0)]
        return out
    corpus = _fault_corpus()
    # WHEN the link comparison runs on them THEN it fails
    for mutant in (seq_off, no_crc):
        with pytest.raises(AssertionError):
            _assert_same_links(corpus, mutant)


def test_the_service_picks_the_core_scan_unless_told_python(monkeypatch):
    # GIVEN AZIMUTHD_CORE=python THEN the link keeps the Python scan
    assert link_core.frame_scan({"AZIMUTHD_CORE": "python"}) is None
    # and a Daemon's link gets what link_core gives (the core's when built)
    from service.config import validate
    from service.daemon import Daemon
    import tempfile
    monkeypatch.delenv("AZIMUTHD_CORE", raising=False)
    d = Daemon(validate({"zenoh": {"enabled": False}, "service": {"state_dir": tempfile.mkdtemp()},
                         "mavlink": {"url": "udpin:127.0.0.1:0"}, "site": {"lat_deg": -35.36, "lon_deg": 149.16}}))
    d.open()
    try:
        scan = d.link._parser.scan
        if CORE_SCAN is None:
            assert scan is frame_scan.split_raw_imu
        else:
            assert scan is not frame_scan.split_raw_imu and scan.func is CORE_SCAN.func
    finally:
        d.close()
