"""The receive path never raises on bad bytes, and a valid frame after garbage still decodes."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.imu_batch import ImuBatch
from mavlink_io.link import LinkConfig, MavlinkLink
from mavlink_io.samples import ImuSample
from mavlink_io.transport import NullTransport


def _link(imu_batch: bool = False):
    t = [0.0]
    return MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", imu_batch=imu_batch), clock=lambda: t[0],
                       transport=NullTransport(None))


def _frames():
    fc = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    out = [mavlink2.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3).pack(fc)]
    for k in range(5):
        out.append(mavlink2.MAVLink_raw_imu_message(1_000_000 + 5000 * k, 1, 2, -1000, 3, 4, 5, 6, 7, 8, 0, 0).pack(fc))
        out.append(mavlink2.MAVLink_attitude_message(1000 + 5 * k, 0.1, 0.2, 0.3, 0, 0, 0).pack(fc))
        out.append(mavlink2.MAVLink_highres_imu_message(1_000_000 + 5000 * k, 0, 0, -9.8, 0, 0, 0, 0.2, 0, 0.4,
                                                        1000.0, 1.0, 0, 20.0, 0x1FFF, 0).pack(fc))
    return b"".join(out)


FRAMES = _frames()


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.binary(max_size=600))
def test_random_bytes_never_raise(data):
    link = _link()
    link.feed(data, 0.0)
    link.poll(0.0)
    # and the link still decodes a good stream afterwards
    items = link.feed(b"\x00" * 300 + FRAMES, 1.0)  # 300 zeros: flush any half-frame length claim
    assert sum(isinstance(i, ImuSample) for i in items) >= 1


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.integers(0, len(FRAMES) - 1), st.integers(0, 255)), min_size=1, max_size=20),
       st.integers(1, 64))
def test_mutated_frames_never_raise_and_are_counted(flips, chunk):
    data = bytearray(FRAMES)
    for pos, val in flips:
        data[pos] = val
    link = _link()
    items = []
    for i in range(0, len(data), chunk):  # arbitrary fragmentation, as a serial port delivers
        items += link.feed(bytes(data[i:i + chunk]), 0.001 * i)
    s = link.stats
    assert s.parser_errors == 0
    good_t = {1.0 + 0.005 * k for k in range(5)}
    for it in items:
        if isinstance(it, ImuSample):  # whatever got through is an original sample (CRC held)
            assert round(it.time_fc_s, 6) in {round(t, 6) for t in good_t}
            assert np.all(np.isfinite(it.gyro_rad_s)) and np.all(np.isfinite(it.accel_m_s2))
    if bytes(data) != FRAMES:  # every byte is a frame's magic, or CRC-protected, or its msgid
        assert s.crc_errors + s.framing_errors + s.unknown_ids >= 1  # (unknown id: no CRC extra)


def _same(a, b) -> bool:
    """Two link items field by field (numpy arrays by value)."""
    if type(a) is not type(b):
        return False
    for name in getattr(a, "__dataclass_fields__", ()):
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if x is None or y is None or not np.array_equal(x, y, equal_nan=True):
                return False
        elif x != y and not (x != x and y != y):  # NaN == NaN here
            return False
    return True


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.integers(0, len(FRAMES) - 1), st.integers(0, 255)), min_size=0, max_size=20),
       st.integers(1, 400), st.booleans())
def test_the_batch_path_reads_every_mutated_stream_as_the_message_path(flips, chunk, datagram):
    # GIVEN the frames with some bytes changed, cut into reads of any size, as a stream or datagrams
    data = bytearray(FRAMES)
    for pos, val in flips:
        data[pos] = val
    out = {}
    for batch in (False, True):
        # WHEN a link with and one without the IMU batch path read them
        link = _link(imu_batch=batch)
        items, rows = [], 0
        for i in range(0, len(data), chunk):
            for it in link.feed(bytes(data[i:i + chunk]), 0.001 * i, datagram=datagram):
                rows += len(it) if isinstance(it, ImuBatch) else 0
                items += it.samples() if isinstance(it, ImuBatch) else [it]
        out[batch] = items, link.stats.as_dict()
    if not flips and not datagram:  # a clean byte stream: every RAW_IMU took the batch path
        assert rows == 5
    # THEN the same items (the batches' samples in their places) and the same counters
    (items0, stats0), (items1, stats1) = out[False], out[True]
    assert len(items1) == len(items0) and all(_same(a, b) for a, b in zip(items1, items0))
    assert stats1 == stats0


def test_sequence_counter_restart_resyncs():
    fc = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    link = _link()
    link.feed(mavlink2.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3).pack(fc), 0.0)
    data = b""
    for boot in range(2):
        fc.seq = 0  # the FC restarted: its sequence counter too
        for k in range(10):
            data += mavlink2.MAVLink_attitude_message(100 * boot + k, 0, 0, 0, 0, 0, 0).pack(fc)
            fc.seq = (fc.seq + 1) % 256
    link.feed(data, 1.0)
    assert link.stats.seq_lost == 0 and link.stats.seq_reordered == 2 and link.stats.seq_duplicates == 1


def test_subscriber_sees_raw_messages_and_its_errors_are_contained():
    fc = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    link = _link()
    seen = []

    def bad(msg):
        seen.append(msg.get_type())
        raise RuntimeError("boom")
    link.subscribe(bad)
    items = link.feed(mavlink2.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3).pack(fc)
                      + mavlink2.MAVLink_vfr_hud_message(1, 2, 3, 4, 5, 6).pack(fc), 0.0)
    assert seen == ["HEARTBEAT", "VFR_HUD"] and link.stats.subscriber_errors == 2
    assert "boom" in link.last_error and any(getattr(i, "kind", "") == "autopilot_detected" for i in items)


def test_fixed_imu_source_requests_only_that_stream():
    fc = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    t = [0.0]
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", imu_source="SCALED_IMU",
                                  stream_rates_hz={"RAW_IMU": 200.0, "SCALED_IMU": 100.0, "ATTITUDE": 10.0}),
                       clock=lambda: t[0], transport=NullTransport(None))
    items = link.feed(mavlink2.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3).pack(fc), 0.0)
    req = [i for i in items if getattr(i, "kind", "") == "rates_requested"][0]
    assert "SCALED_IMU 100 Hz" in req.detail and "RAW_IMU" not in req.detail
    items = link.feed(mavlink2.MAVLink_raw_imu_message(1000, 0, 0, -1000, 0, 0, 0, 0, 0, 0, 0, 0).pack(fc)
                      + mavlink2.MAVLink_scaled_imu_message(1, 0, 0, -1000, 0, 0, 0, 0, 0, 0, 0).pack(fc), 0.1)
    assert [i.source for i in items if isinstance(i, ImuSample)] == ["SCALED_IMU"]
