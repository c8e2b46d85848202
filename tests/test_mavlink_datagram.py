"""UDP: the parser is reset at a datagram that starts a new frame while a damaged frame is still
held (a lying length byte no longer swallows the next datagrams' intact frames); a sender that
splits frames across datagrams (serial-to-UDP bridge) is recognised and parsed as a byte stream;
the transport's kernel drop counter reaches LinkStats."""
from __future__ import annotations

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.samples import ImuSample
from mem_transport import DropsTransport, MemTransport


class Clock:
    t = 10.0

    def __call__(self):
        return self.t


def make(datagram=True, transport=None):
    clock = Clock()
    tr = transport or MemTransport(datagram)
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", system_id=1), clock=clock, transport=tr)
    return link, tr, clock


FC = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)


def pack(msg) -> bytes:
    buf = bytes(msg.pack(FC))
    FC.seq = (FC.seq + 1) % 256
    return buf


def heartbeat() -> bytes:
    return pack(mavlink2.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3))


def imu(k: int) -> bytes:
    return pack(mavlink2.MAVLink_raw_imu_message(1_000_000 + 5000 * k, k % 50 - 25, 2, -1000, 3, -4, 5,
                                                 200, -10, 400, 0, 0))


def damaged_long(k: int) -> bytes:
    f = bytearray(imu(k))
    f[1] = 250  # the length byte lies: the parser waits for 250 payload bytes
    return bytes(f)


def n_imu(items) -> int:
    return sum(isinstance(i, ImuSample) for i in items)


def run_poll(link, tr, datagrams) -> list:
    items = []
    for d in datagrams:
        tr.inbox.append(d)
        items += link.poll()
    return items


def test_damaged_frame_does_not_swallow_the_next_datagrams():
    link, tr, _ = make(datagram=True)
    items = run_poll(link, tr, [heartbeat(), damaged_long(0), imu(1), imu(2), damaged_long(3), imu(4)])
    assert n_imu(items) == 3
    assert link.stats.datagram_resets == 2 and link.stats.udp_split_frames_seen == 0
    assert link.stats.accepted + link.stats.seq_lost == 6 and link.stats.seq_lost == 2


def test_stream_transport_is_parsed_as_before():
    """TCP/serial: a chunk boundary means nothing, no reset: the damaged frame swallows its
    neighbours as every MAVLink parser does."""
    link, tr, _ = make(datagram=False)
    items = run_poll(link, tr, [heartbeat(), damaged_long(0), imu(1), imu(2)])
    assert n_imu(items) < 2 and link.stats.datagram_resets == 0


def test_garbage_datagram_after_a_damaged_frame_does_not_switch_to_stream_mode():
    link, tr, _ = make()
    items = run_poll(link, tr, [heartbeat(), damaged_long(0), b"\x00\x11garbage" * 3, imu(1), imu(2)])
    assert n_imu(items) == 2 and link.stats.udp_split_frames_seen == 0
    assert not [i for i in items if isinstance(i, LinkEvent) and i.kind == "udp_split_frames"]


def _split(data: bytes, rng, max_len: int) -> list[bytes]:
    cuts = np.cumsum(rng.integers(1, max_len + 1, size=len(data)))
    cuts = [0, *[int(c) for c in cuts if c < len(data)], len(data)]
    return [data[a:b] for a, b in zip(cuts[:-1], cuts[1:])]


def test_split_sender_is_learnt_and_loses_nothing():
    rng = np.random.default_rng(3)
    frames = [heartbeat()] + [imu(k) for k in range(1, 400)]
    link, tr, _ = make()
    items = run_poll(link, tr, _split(b"".join(frames), rng, 40))
    assert n_imu(items) == 399 and link.stats.seq_lost == 0
    assert link.stats.udp_split_frames_seen > 100
    ev = [i for i in items if isinstance(i, LinkEvent) and i.kind == "udp_split_frames"]
    assert len(ev) == 1 and "no parser reset per datagram" in ev[0].detail


def test_split_sender_whose_fragment_starts_with_a_magic_byte_before_learning():
    """The one case the rule loses frames a byte-stream parse would keep: before the sender is
    learnt, a fragment that happens to start with 0xFD/0xFE resets a genuine partial frame."""
    link, tr, _ = make()
    run_poll(link, tr, [heartbeat()])
    f1 = pack(mavlink2.MAVLink_raw_imu_message(1_005_000, -3, 2, -1000, 3, -4, 5, 200, -10, 400, 0, 0))
    cut = 10 + 8  # header, time_usec: xacc = -3 is the bytes FD FF
    assert f1[cut] == 0xFD
    rest = b"".join(imu(k) for k in range(2, 40))
    datagrams = [f1[:cut], f1[cut:] + rest[:7]] + _split(rest[7:], np.random.default_rng(1), 30)
    items = run_poll(link, tr, datagrams)
    # measured: 2 resets, frames 1 and 2 lost (the reset frame's tail FD FF.. parses as a frame
    # claiming 255 bytes, which holds the next fragments until a real frame start resets again);
    # learnt right after, nothing lost from then on
    assert 1 <= link.stats.datagram_resets <= 3
    assert 36 <= n_imu(items) <= 38
    assert link.stats.udp_split_frames_seen > 0 and link._udp_split_sender
    assert link.stats.accepted + link.stats.seq_lost == 40


def test_split_learning_is_forgotten_when_the_transport_reopens():
    link, tr, clock = make()
    run_poll(link, tr, _split(heartbeat() + imu(1) + imu(2), np.random.default_rng(0), 10))
    assert link._udp_split_sender
    tr.die = True
    link.poll()
    clock.t += 10.0
    link.poll()  # reopened after the backoff
    assert not link._udp_split_sender
    items = run_poll(link, tr, [damaged_long(3), imu(4)])
    assert n_imu(items) == 1 and link.stats.datagram_resets == 1


def test_kernel_rx_drops_in_stats():
    link, tr, clock = make(transport=DropsTransport(drops=17))
    assert link.stats.kernel_rx_drops is None
    clock.t += 1.5
    link.poll()
    assert link.stats.kernel_rx_drops == 17 and link.stats.as_dict()["kernel_rx_drops"] == 17
    tr.drops = 20
    clock.t += 0.3
    link.poll()
    assert link.stats.kernel_rx_drops == 17  # refreshed at most once a second
    clock.t += 1.0
    link.poll()
    assert link.stats.kernel_rx_drops == 20
    tr.drops = 25
    tr.die = True  # the socket dies: its count is kept, the new socket counts from 0
    link.poll()
    assert link.stats.kernel_rx_drops == 25
    tr.drops = 4
    clock.t += 10.0
    link.poll()
    assert link.stats.kernel_rx_drops == 29
    link2, _, clock2 = make()
    clock2.t += 2.0
    link2.poll()
    assert link2.stats.kernel_rx_drops is None  # the transport cannot tell
