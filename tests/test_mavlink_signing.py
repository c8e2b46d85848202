"""MAVLink 2 signing in MavlinkLink: what we send verifies with an independent implementation of the
spec and with a pymavlink peer; what we receive is verified in the order that resists a forged
far-future timestamp; the require_signed policy; the outgoing timestamp's clock rules; no key
material in anything printable."""
from __future__ import annotations

import base64
import hashlib
import json

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io import signing
from mavlink_io.link import LINK_EVENT_KINDS, LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.samples import FcHeartbeat, ImuSample, IncomingCommand
from mem_transport import MemTransport

KEY = hashlib.sha256(b"azimuthd test key").digest()
OTHER_KEY = hashlib.sha256(b"not our key").digest()
NOW_UNIX_S = 1_763_800_000.0  # 2025-11-22
EPOCH_2015 = 1_420_070_400
TS_NOW = int((NOW_UNIX_S - EPOCH_2015) * 100_000)
FC, GCS = (1, 1), (255, 190)
US = 191


class Clocks:
    def __init__(self):
        self.mono = 100.0
        self.wall = NOW_UNIX_S


def make_link(key=KEY, clocks=None, **kw):
    clocks = clocks or Clocks()
    tr = MemTransport()
    cfg = LinkConfig(url="udpin:127.0.0.1:0", system_id=1, signing_key=key, **kw)
    link = MavlinkLink(cfg, clock=lambda: clocks.mono, transport=tr, wall_clock=lambda: clocks.wall)
    return link, tr, clocks


def peer(src=FC, key=None, ts=TS_NOW, link_id=0):
    m = mavlink2.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    if key is not None:
        m.signing.secret_key = key
        m.signing.sign_outgoing = True
        m.signing.timestamp = ts
        m.signing.link_id = link_id
    return m


def pack(mav, msg) -> bytes:
    buf = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return buf


def hb():
    return mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_FIXED_WING, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              0, 0, mavlink2.MAV_STATE_ACTIVE, 3)


def raw_imu(k):
    return mavlink2.MAVLink_raw_imu_message(1_000_000 + 5000 * k, 1, 2, -1000, 3, 4, 5, 200, 10, 400, 0, 0)


def cmd_long(target=(1, US), command=mavlink2.MAV_CMD_DO_SET_MODE):
    return mavlink2.MAVLink_command_long_message(target[0], target[1], command, 0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0)


def events(items, kind):
    return [i for i in items if isinstance(i, LinkEvent) and i.kind == kind]


# --- an independent implementation of the spec (hashlib only, not mavlink_io.signing) --------------

def spec_verify(frame: bytes, key: bytes) -> tuple[int, int]:
    """Check a signed MAVLink 2 frame by the spec; return (link_id, timestamp)."""
    assert frame[0] == 0xFD and frame[2] & 0x01, "not a signed MAVLink 2 frame"
    payload_len = frame[1]
    assert len(frame) == 10 + payload_len + 2 + 13
    signed_part = frame[:10 + payload_len + 2 + 7]  # header + payload + CRC + link_id + timestamp
    assert hashlib.sha256(key + signed_part).digest()[:6] == frame[-6:], "signature mismatch"
    link_id = frame[-13]
    timestamp = int.from_bytes(frame[-12:-6], "little")
    return link_id, timestamp


# --- (a) what we send -------------------------------------------------------------------------------

def test_outgoing_frames_verify_with_an_independent_implementation_of_the_spec():
    link, tr, clocks = make_link(signing_link_id=7)
    link.poll()  # heartbeat
    link.send(link.mav.attitude_encode(10, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0))
    link.send(link.mav.named_value_float_encode(11, b"azimuth", 1.5))
    assert len(tr.sent) >= 3  # heartbeat(s), ATTITUDE, NAMED_VALUE_FLOAT
    stamps = []
    for f in tr.sent:
        link_id, ts = spec_verify(f, KEY)
        assert link_id == 7
        stamps.append(ts)
    assert TS_NOW < stamps[0] < TS_NOW + 100  # from the wall clock, 10 us units since 2015
    assert stamps == sorted(set(stamps))  # strictly increasing
    with pytest.raises(AssertionError, match="signature mismatch"):
        spec_verify(tr.sent[0], OTHER_KEY)


def test_outgoing_frames_verify_in_a_pymavlink_peer_with_the_same_key():
    """Interop: a pymavlink receiver with the key (as MAVProxy / ArduPilot check) accepts them."""
    link, tr, _ = make_link()
    link.poll()
    link.send(link.mav.attitude_encode(10, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0))
    rx = peer(key=KEY, ts=TS_NOW)
    rx.signing.sign_outgoing = False
    msgs = [rx.parse_buffer(f)[0] for f in tr.sent]
    assert {m.get_type() for m in msgs[:-1]} == {"HEARTBEAT"} and msgs[-1].get_type() == "ATTITUDE"
    assert all(m._signed for m in msgs) and rx.signing.goodsig_count == len(msgs) and rx.signing.badsig_count == 0
    wrong = peer(key=OTHER_KEY, ts=TS_NOW)
    wrong.robust_parsing = True
    assert wrong.parse_buffer(tr.sent[-1])[0].get_type() == "BAD_DATA"


def test_sign_outgoing_false_sends_unsigned_but_still_verifies_incoming():
    link, tr, _ = make_link(sign_outgoing=False)
    link.poll()
    assert tr.sent and not tr.sent[0][2] & 0x01
    bad = pack(peer(key=OTHER_KEY), hb())
    link.feed(bad)
    assert link.stats.signature_bad == 1


# --- (b) what we receive --------------------------------------------------------------------------

def test_signed_frames_from_a_pymavlink_peer_are_accepted():
    link, _, _ = make_link(require_signed="all")
    fc = peer(key=KEY)
    items = link.feed(pack(fc, hb()) + pack(fc, raw_imu(0)) + pack(fc, raw_imu(1)))
    assert sum(isinstance(i, FcHeartbeat) for i in items) == 1
    assert sum(isinstance(i, ImuSample) for i in items) == 2
    assert link.stats.signed_accepted == 3 and link.stats.signature_bad == 0
    gcs = peer(GCS, key=KEY)
    cmds = [i for i in link.feed(pack(gcs, cmd_long())) if isinstance(i, IncomingCommand)]
    assert len(cmds) == 1 and cmds[0].signed is True


def test_wrong_key_is_dropped_counted_and_reported():
    link, _, _ = make_link()
    link.feed(pack(peer(key=KEY), hb()))
    items = link.feed(pack(peer(GCS, key=OTHER_KEY), cmd_long()) + pack(peer(key=OTHER_KEY), raw_imu(0)))
    assert not any(isinstance(i, (IncomingCommand, ImuSample)) for i in items)
    assert link.stats.signature_bad == 2 and link.stats.signature_replay == 0
    ev = events(items, "signature_rejected")
    assert len(ev) == 1  # rate-limited: the second one is held back
    assert "system 255 component 190" in ev[0].detail and "COMMAND_LONG" in ev[0].detail
    assert "does not match" in ev[0].detail


def test_altered_signed_frame_is_dropped():
    link, _, _ = make_link()
    f = bytearray(pack(peer(key=KEY), raw_imu(0)))
    f[-10] ^= 0x01  # a timestamp bit: the signature no longer matches (CRC still fine)
    link.feed(pack(peer(key=KEY, link_id=3), hb()))
    assert not any(isinstance(i, ImuSample) for i in link.feed(bytes(f)))
    assert link.stats.signature_bad == 1


def test_replayed_frame_is_dropped():
    link, _, _ = make_link()
    fc = peer(key=KEY)
    first = pack(fc, hb())
    imu = pack(fc, raw_imu(0))
    link.feed(first + imu)
    items = link.feed(imu)  # the same bytes again
    assert not any(isinstance(i, ImuSample) for i in items)
    assert link.stats.signature_replay == 1 and link.stats.signed_accepted == 2
    assert "replay" in events(items, "signature_rejected")[0].detail


def test_new_stream_more_than_60_s_behind_is_rejected_and_within_60_s_accepted():
    link, _, _ = make_link()
    old = peer(GCS, key=KEY, ts=TS_NOW - 6_100_000)
    link.feed(pack(old, cmd_long()))
    assert link.stats.signature_replay == 1
    ok = peer((250, 190), key=KEY, ts=TS_NOW - 5_900_000)
    assert any(isinstance(i, IncomingCommand) for i in link.feed(pack(ok, cmd_long())))


# --- (c) the forged far-future timestamp ------------------------------------------------------------

def test_forged_far_future_timestamp_does_not_block_the_genuine_stream():
    link, _, _ = make_link()
    fc = peer(key=KEY)
    attacker = peer(FC, key=OTHER_KEY, ts=TS_NOW + 100 * 365 * 86400 * 100_000)  # same stream, +100 years
    forged = pack(attacker, raw_imu(0))
    link.feed(pack(fc, hb()))
    link.feed(forged)
    assert link.stats.signature_bad == 1
    items = link.feed(pack(fc, raw_imu(1)) + pack(fc, raw_imu(2)))
    assert sum(isinstance(i, ImuSample) for i in items) == 2
    assert link.stats.signature_replay == 0
    # our outgoing clock did not follow the forged timestamp either
    assert link.signing_timestamp < TS_NOW + 1000


def test_pymavlink_own_check_is_blocked_by_the_forged_frame():
    """Why the link does not let pymavlink verify: its check_signature stores the stream's
    timestamp before comparing the signature, so the genuine frames after a forged one fail."""
    fc = peer(key=KEY)
    attacker = peer(FC, key=OTHER_KEY, ts=TS_NOW + 100 * 365 * 86400 * 100_000)
    rx = peer((1, US), key=KEY, ts=TS_NOW)
    rx.robust_parsing = True
    assert rx.parse_buffer(pack(fc, hb()))[0].get_type() == "HEARTBEAT"
    assert rx.parse_buffer(pack(attacker, raw_imu(0)))[0].get_type() == "BAD_DATA"
    genuine = rx.parse_buffer(pack(fc, raw_imu(1)) + pack(fc, raw_imu(2)))
    assert [m.get_type() for m in genuine] == ["BAD_DATA", "BAD_DATA"]  # blocked: the DoS
    assert rx.signing.badsig_count == 3


# --- (d) policy ------------------------------------------------------------------------------------

def test_policy_commands_drops_unsigned_command_to_us_and_accepts_unsigned_telemetry():
    link, _, _ = make_link(require_signed="commands")
    fc = peer()  # unsigned
    items = link.feed(pack(fc, hb()) + pack(fc, raw_imu(0)))
    assert sum(isinstance(i, ImuSample) for i in items) == 1
    gcs = peer(GCS)
    items = link.feed(pack(gcs, cmd_long()) + pack(gcs, cmd_long(target=(0, 0)))
                      + pack(gcs, cmd_long(target=(1, 1))))  # the last is for the FC: not ours to judge
    assert not any(isinstance(i, IncomingCommand) for i in items)
    assert link.stats.unsigned_commands_rejected == 2 and link.stats.unsigned_rejected == 2
    ev = events(items, "unsigned_command_rejected")
    assert len(ev) == 1 and "COMMAND_LONG" in ev[0].detail and "system 255 component 190" in ev[0].detail
    assert link.stats.foreign_messages == 1


def test_policy_all_drops_unsigned_telemetry():
    link, _, _ = make_link(require_signed="all")
    fc = peer()
    items = link.feed(pack(fc, hb()) + pack(fc, raw_imu(0)))
    assert not any(isinstance(i, (ImuSample, FcHeartbeat)) for i in items)
    assert link.fc_autopilot is None  # an unsigned heartbeat does not teach us the autopilot
    assert link.stats.unsigned_rejected == 2 and link.stats.unsigned_commands_rejected == 0


def test_policy_none_accepts_unsigned_commands():
    link, _, _ = make_link(require_signed="none")
    items = link.feed(pack(peer(GCS), cmd_long()))
    cmds = [i for i in items if isinstance(i, IncomingCommand)]
    assert len(cmds) == 1 and cmds[0].signed is False
    assert link.stats.unsigned_rejected == 0


def test_without_a_key_signed_frames_decode_but_are_not_marked_signed():
    link, tr, _ = make_link(key=None)
    assert link.signing_timestamp is None
    items = link.feed(pack(peer(GCS, key=OTHER_KEY), cmd_long()))
    cmds = [i for i in items if isinstance(i, IncomingCommand)]
    assert len(cmds) == 1 and cmds[0].signed is False
    link.poll()
    assert tr.sent and not tr.sent[0][2] & 0x01


def test_security_events_are_rate_limited_with_a_count():
    link, _, clocks = make_link()
    gcs = peer(GCS)
    reported = []
    for k in range(100):  # 100 unsigned commands over 20 s
        clocks.mono = 100.0 + 0.2 * k
        reported += events(link.feed(pack(gcs, cmd_long()), clocks.mono), "unsigned_command_rejected")
        reported += events(link.poll(), "unsigned_command_rejected")
    clocks.mono += 30.0
    reported += events(link.poll(), "unsigned_command_rejected")
    assert link.stats.unsigned_commands_rejected == 100
    assert len(reported) == 3  # at 0 s, after 10 s (with the count), the rest flushed later
    assert "more since the last report" in reported[1].detail
    counts = [int(e.detail.split(" more")[0].split("(")[-1]) for e in reported[1:]]
    assert 2 + sum(counts) == 100  # the first two reports are about a frame each, plus the held-back counts
    assert "signature_rejected" in LINK_EVENT_KINDS and "unsigned_command_rejected" in LINK_EVENT_KINDS


# --- (e) the outgoing timestamp ------------------------------------------------------------------------

def test_outgoing_timestamp_never_goes_back_and_starts_above_the_floor():
    floor = TS_NOW + 50_000_000  # a persisted timestamp 500 s ahead of the wall clock
    link, tr, clocks = make_link(signing_timestamp_floor=floor)
    assert link.signing_timestamp > floor
    seen = []
    for step_s in (1.1, -3600.0, 1.1, 7200.0, -7200.0, 1.1):
        clocks.mono += 1.1
        clocks.wall += step_s
        link.poll()
        link.send(link.mav.attitude_encode(0, 0, 0, 0, 0, 0, 0))
        seen.append(link.signing_timestamp)
    stamps = [spec_verify(f, KEY)[1] for f in tr.sent]
    assert stamps == sorted(set(stamps)) and stamps[0] > floor
    assert seen == sorted(seen)
    # the wall clock stepped forward past the floor: followed (within the 1 s refresh)
    assert max(stamps) >= int((NOW_UNIX_S + 1.1 - 3600 + 1.1 + 7200 - EPOCH_2015) * 100_000)


def test_board_without_rtc_starts_at_the_floor_and_follows_a_valid_peer():
    clocks = Clocks()
    clocks.wall = 0.0  # 1970: no RTC
    link, tr, _ = make_link(clocks=clocks, signing_timestamp_floor=12345)
    assert link.signing_timestamp == 12346
    fc = peer(key=KEY, ts=TS_NOW)
    link.feed(pack(fc, hb()))
    assert link.signing_timestamp >= TS_NOW  # the spec's rule: at least the newest valid one seen


def test_signing_config_validation():
    for bad in (b"x" * 31, b"x" * 33, "k" * 32, 123):
        with pytest.raises(ValueError, match="signing_key"):
            LinkConfig(url="udpin:127.0.0.1:0", signing_key=bad)
    with pytest.raises(ValueError, match="require_signed"):
        LinkConfig(url="udpin:127.0.0.1:0", signing_key=KEY, require_signed="some")
    with pytest.raises(ValueError, match="signing_link_id"):
        LinkConfig(url="udpin:127.0.0.1:0", signing_key=KEY, signing_link_id=256)
    with pytest.raises(ValueError, match="signing_timestamp_floor"):
        LinkConfig(url="udpin:127.0.0.1:0", signing_key=KEY, signing_timestamp_floor=-1)
    with pytest.raises(ValueError, match="sign_outgoing"):
        LinkConfig(url="udpin:127.0.0.1:0", signing_key=KEY, sign_outgoing="yes")


# --- (f) no key material anywhere printable ---------------------------------------------------------------

def _key_forms(key: bytes) -> list[str]:
    return [key.hex(), key.hex().upper(), base64.b64encode(key).decode(), base64.urlsafe_b64encode(key).decode(),
            repr(key), str(list(key)), key.decode("latin-1"), key[:8].hex()]


def test_no_key_material_in_repr_stats_events_or_errors():
    link, tr, clocks = make_link()
    items = []
    items += link.feed(pack(peer(GCS, key=OTHER_KEY), cmd_long()))
    items += link.feed(pack(peer(GCS), cmd_long()))
    f = pack(peer(key=KEY), hb())
    items += link.feed(f + f)
    link.send(object())  # a send error sets last_error
    clocks.mono += 20.0
    items += link.poll()
    texts = [repr(link.cfg), str(link.cfg), json.dumps(link.stats.as_dict(), default=str), str(link.last_error),
             repr(link._verifier)]
    texts += [repr(i) for i in items]
    try:
        LinkConfig(url="udpin:127.0.0.1:0", signing_key=KEY[:31])
    except ValueError as exc:
        texts.append(str(exc))
    assert events(items, "signature_rejected") and link.last_error
    blob = "\n".join(texts)
    for form in _key_forms(KEY) + _key_forms(OTHER_KEY):
        assert form not in blob
    # nor the signature bytes of the rejected frame
    assert f[-6:].hex() not in blob
    assert LinkConfig(url="udpin:127.0.0.1:0", signing_key=KEY) == LinkConfig(url="udpin:127.0.0.1:0")


# --- the pure module --------------------------------------------------------------------------------------

def test_verifier_records_a_stream_only_after_both_checks():
    v = signing.SignatureVerifier(KEY)
    good = pack(peer(key=KEY, ts=1000), hb())
    bad = pack(peer(key=OTHER_KEY, ts=10**12), hb())
    assert v.verify(bad, 1, 1, 1000).reason == signing.REASON_BAD_SIGNATURE and v.streams == {}
    assert v.verify(good, 1, 1, 1000).ok and v.streams == {(0, 1, 1): 1000}
    r = v.verify(good, 1, 1, 1000)
    assert r.reason == signing.REASON_OLD_TIMESTAMP and r.replay
    assert v.verify(b"\xfd\x00\x01", 1, 1, 0).reason == signing.REASON_MALFORMED
    assert signing.timestamp_from_unix_s(EPOCH_2015 + 1.5) == 150_000
    assert signing.timestamp_from_unix_s(0.0) == 0
