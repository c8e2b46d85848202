"""The daemon's output frames packed without pymavlink's per-send objects (mavlink_io/frame_pack.py,
issue 19) are pymavlink's frames byte for byte, and the sender advances as pymavlink's send does."""
from __future__ import annotations

import math
import random

import pytest
from pymavlink.dialects.v20 import ardupilotmega, common

from mavlink_io import frame_pack
from mavlink_io.outputs import _named_value


class _File:
    def __init__(self):
        self.frames: list[bytes] = []

    def write(self, buf) -> None:
        self.frames.append(bytes(buf))


def _messages(mod, rng: random.Random) -> list:
    """Every output type, with values that exercise the payload truncation (zeros at the end, all
    zeros), NaN, -0.0, infinities, extreme integers, and char arrays short and full."""
    def f() -> float:
        return rng.choice([0.0, -0.0, math.nan, math.inf, -math.inf, 1e-40, rng.uniform(-1e6, 1e6),
                           rng.uniform(-4, 4)])
    out = [mod.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
           mod.MAVLink_attitude_message(2**32 - 1, f(), f(), f(), 0.0, 0.0, 0.0)]
    for _ in range(40):
        out.append(mod.MAVLink_attitude_message(rng.randrange(2**32), *(f() for _ in range(6))))
        out.append(mod.MAVLink_attitude_quaternion_message(rng.randrange(2**32), *(f() for _ in range(7)),
                                                           [f() for _ in range(4)]))
        out.append(mod.MAVLink_odometry_message(
            rng.randrange(2**64), rng.randrange(256), rng.randrange(256), f(), f(), f(), [f() for _ in range(4)],
            f(), f(), f(), f(), f(), f(), [f() for _ in range(21)], [f() if rng.random() < 0.5 else 0.0
                                                                      for _ in range(21)],
            rng.randrange(256), rng.randrange(256), rng.randrange(-128, 128)))
        name = "".join(rng.choice("abcdefgh_") for _ in range(rng.randrange(1, 11)))
        out.append(mod.MAVLink_named_value_float_message(rng.randrange(2**32), name.encode(), f()))
    out.append(mod.MAVLink_odometry_message(0, 0, 0, 0, 0, 0, [0] * 4, 0, 0, 0, 0, 0, 0, [0] * 21, [0] * 21,
                                            0, 0, 0))
    return out


@pytest.mark.parametrize("mod", [common, ardupilotmega], ids=["common", "ardupilotmega"])
def test_output_frames_are_pymavlinks_byte_for_byte(mod):
    # GIVEN two senders with one identity, and ~160 output messages over 300 sequence numbers
    rng = random.Random(19)
    msgs = _messages(mod, rng) + [_named_value(123, "az_deg", 12.5)]
    ref_file, fast_file = _File(), _File()
    ref = ardupilotmega.MAVLink(ref_file, srcSystem=42, srcComponent=191)
    fast = ardupilotmega.MAVLink(fast_file, srcSystem=42, srcComponent=191)
    # WHEN pymavlink sends them with one, frame_pack with the other
    for _ in range(2):
        for m in msgs:
            ref.send(m)
            frame_pack.send(fast, m)
    # THEN every frame is the same bytes (through the sequence wrap), and so are the senders' counts
    assert all(type(m) in frame_pack._KINDS for m in msgs)
    assert len(fast_file.frames) == len(ref_file.frames) == 2 * len(msgs) > 256
    bad = [i for i, (a, b) in enumerate(zip(ref_file.frames, fast_file.frames)) if a != b]
    assert bad == []
    assert (fast.seq, fast.total_packets_sent, fast.total_bytes_sent) == \
        (ref.seq, ref.total_packets_sent, ref.total_bytes_sent)
    # AND what pymavlink parses back from them is the messages sent
    rx = ardupilotmega.MAVLink(None)
    back = [rx.decode(bytearray(b)) for b in fast_file.frames[:len(msgs)]]
    assert [b.get_type() for b in back] == [m.get_type() for m in msgs]


def test_a_signing_sender_and_other_messages_go_through_pymavlink():
    # GIVEN a signing sender and a message type the module does not pack
    f_ref, f_fast = _File(), _File()
    key = bytes(range(32))
    ref = ardupilotmega.MAVLink(f_ref, srcSystem=1, srcComponent=191)
    fast = ardupilotmega.MAVLink(f_fast, srcSystem=1, srcComponent=191)
    for mav in (ref, fast):
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = key, True, 1
        mav.signing.timestamp = 1000
    att = common.MAVLink_attitude_message(5, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)
    hb = common.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)
    # WHEN both send them
    for m in (att, hb):
        ref.send(m)
        frame_pack.send(fast, m)
    # THEN the frames are pymavlink's (signed: 13 bytes longer, the signing timestamp advanced)
    assert f_fast.frames == f_ref.frames and fast.signing.timestamp == ref.signing.timestamp == 1002
    assert len(f_fast.frames[0]) == len(frame_pack.frame(att, 0, 1, 191)) + 13
