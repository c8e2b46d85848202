"""Stream rates against ArduPilot's refusals: the bundled simulator with the ardupilot personality
refuses a rate the way ArduPlane SITL did (COMMAND_ACK DENIED and a two-chunk STATUSTEXT "Requested
rate for message ID 27 too fast. Increase SCHED_LOOP_RATE" above 0.8 x SCHED_LOOP_RATE); the link asks
again lower, measures what it gets, falls back to REQUEST_DATA_STREAM for a stream not delivered, and
says which FC parameter to change. In memory, on the simulator's clock: nothing depends on timing."""
from __future__ import annotations

import struct

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io import decode as dec
from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.rates import Finished, RateRequester, SendInterval
from sim.autopilot import ACCEPTED, RAW_IMU, Autopilot
from mem_transport import MemTransport


class _ToLink:
    """The simulator's connection: what it writes lands in the link's inbox."""

    def __init__(self, transport: MemTransport, sysid: int, compid: int):
        self.transport = transport
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=compid)

    def write(self, buf):
        self.transport.inbox.append(bytes(buf))


class SimLoop:
    """The bundled simulator and a MavlinkLink wired in memory; time is the simulator's."""

    def __init__(self, ap: Autopilot, stream_rates_hz: dict, **link_kw):
        self.ap = ap
        self.tr = MemTransport()
        ap.conn = _ToLink(self.tr, ap.sysid, ap.compid)
        self.link = MavlinkLink(LinkConfig(url="udpin:0.0.0.0:0", stream_rates_hz=stream_rates_hz, **link_kw),
                                clock=lambda: self.ap.t, transport=self.tr)
        self._parser = mavlink2.MAVLink(None)
        self.items: list = []
        self.requests: list = []

    def run(self, until_s: float, step_s: float = 0.004) -> None:
        while self.ap.t < until_s:
            self.ap.t = round(self.ap.t + step_s, 9)
            for mid, st in list(self.ap.streams.items()):
                if st.next_s <= self.ap.t + 1e-9 and self.ap.streams.get(mid) is st:
                    self.ap._send(self.ap._build(mid, st))
                    st.next_s += st.interval_s
                    if st.next_s < self.ap.t:
                        st.next_s = self.ap.t + st.interval_s
            self.items.extend(self.link.poll(0.0))
            sent, self.tr.sent = self.tr.sent, []
            for buf in sent:
                for m in self._parser.parse_buffer(buf) or []:
                    if m.get_type() in ("COMMAND_LONG", "REQUEST_DATA_STREAM", "PARAM_REQUEST_READ"):
                        self.requests.append(m)
                    self.ap._handle(m)

    def events(self, kind: str) -> list[LinkEvent]:
        return [i for i in self.items if isinstance(i, LinkEvent) and i.kind == kind]


WANTED = {"RAW_IMU": 200.0, "SCALED_PRESSURE": 50.0, "ATTITUDE": 50.0}


@pytest.fixture(scope="module")
def stock_loop():
    """GIVEN ArduPilot's stock main loop (SCHED_LOOP_RATE 50: streams up to 40 Hz)
    WHEN the daemon's link asks for RAW_IMU 200 Hz, SCALED_PRESSURE and ATTITUDE 50 Hz."""
    ap = Autopilot("runway_gnss_denied", "udpout:127.0.0.1:9", personality="ardupilot", seed=1)
    ap.params["SCHED_LOOP_RATE"] = 50.0
    loop = SimLoop(ap, WANTED)
    loop.run(12.0)
    return loop


def test_refused_rates_are_asked_again_lower_and_granted(stock_loop):
    # THEN each refused rate is halved until accepted (200 -> 100 -> 50 -> 25 Hz), then two steps
    # halfway back up: 37.5 accepted, 43.75 refused (above 0.8 x 50 = 40 Hz): 37.5 Hz stands
    asked = [(int(m.param1), 1e6 / m.param2) for m in stock_loop.requests
             if m.get_type() == "COMMAND_LONG" and m.command == 511]
    assert [i for i, _ in asked[:6]] == [27] * 6  # param2 travels as float32: compare the rates closely
    assert [hz for _, hz in asked[:6]] == pytest.approx([200.0, 100.0, 50.0, 25.0, 37.5, 43.75], rel=1e-6)
    report = stock_loop.link.stream_report()
    assert {n: r["granted_hz"] for n, r in report.items()} == {"RAW_IMU": 37.5, "SCALED_PRESSURE": 37.5,
                                                                "ATTITUDE": 37.5}
    assert all(r["result"] == "accepted" for r in report.values())
    # the FC's two STATUSTEXT chunks are read as one text
    assert stock_loop.link.rate_refusal_text == "Requested rate for message ID 30 too fast. Increase SCHED_LOOP_RATE"


def test_achieved_rates_are_measured_and_the_parameter_named(stock_loop):
    report = stock_loop.link.stream_report()
    for name in WANTED:  # 37.5 Hz streamed on the simulator's clock, measured over the 2 s window
        assert report[name]["achieved_hz"] == pytest.approx(37.5, abs=1.0), name
    (ev,) = stock_loop.events("rates_limited")  # one line, naming the parameter and the value
    assert "RAW_IMU asked 200 Hz, granted 37.5 Hz" in ev.detail
    assert "SCHED_LOOP_RATE >= 300" in ev.detail  # 200 Hz / 0.8 = 250 -> the next loop rate, 300
    assert "Increase SCHED_LOOP_RATE" in ev.detail  # what the FC said
    assert stock_loop.link.rate_advice is not None
    # the streams were honoured: no legacy REQUEST_DATA_STREAM
    assert not [m for m in stock_loop.requests if m.get_type() == "REQUEST_DATA_STREAM"]


def test_a_fast_enough_loop_grants_everything_and_says_nothing():
    ap = Autopilot("runway_gnss_denied", "udpout:127.0.0.1:9", personality="ardupilot", seed=1)
    ap.params["SCHED_LOOP_RATE"] = 300.0  # 240 Hz allowed
    loop = SimLoop(ap, WANTED)
    loop.run(8.0)
    report = loop.link.stream_report()
    assert {n: r["granted_hz"] for n, r in report.items()} == WANTED
    assert loop.events("rates_limited") == [] and loop.link.rate_advice is None
    assert loop.link.rate_refusal_text is None


class _AcceptsButDoesNotStream(Autopilot):
    """An FC that ACKs SET_MESSAGE_INTERVAL for RAW_IMU but never streams it that way (only the
    legacy stream request works)."""

    def _command(self, msg, is_int):
        if msg.command == 511 and int(msg.param1) == RAW_IMU:
            self._ack(msg, 511, ACCEPTED)
            return
        super()._command(msg, is_int)


def test_accepted_but_not_delivered_falls_back_to_request_data_stream():
    ap = _AcceptsButDoesNotStream("runway_gnss_denied", "udpout:127.0.0.1:9", personality="ardupilot", seed=1)
    loop = SimLoop(ap, {"RAW_IMU": 50.0, "ATTITUDE": 10.0})
    loop.run(9.0)
    rds = [m for m in loop.requests if m.get_type() == "REQUEST_DATA_STREAM"]
    assert [(m.req_stream_id, m.req_message_rate, m.start_stop) for m in rds] == [(1, 50, 1)]
    (ev,) = loop.events("rates_limited")
    assert "RAW_IMU asked 50 Hz, granted 50 Hz, measured 0.0 Hz" in ev.detail
    assert "MAVn_RAW_SENS" in ev.detail and "ATTITUDE" not in ev.detail
    # after the fallback the simulator streams RAW_IMU at the legacy group's rate
    before = loop.link.stats.messages_by_type.get("RAW_IMU", 0)
    loop.run(11.0)
    assert loop.link.stats.messages_by_type.get("RAW_IMU", 0) - before == pytest.approx(100, abs=2)


# --- the pieces -----------------------------------------------------------------------------

def test_rate_requester_bisects_back_up_after_an_acceptance():
    r = RateRequester(ack_timeout_s=0.5, max_tries=2, floor_hz=1.0)
    r.start([("ATTITUDE", 30, 100.0)], 0.0)
    assert r.on_ack(511, 2, 0.1) == [SendInterval("ATTITUDE", 30, 20000.0, 0)]  # 100 refused: 50
    assert r.on_ack(511, 0, 0.2) == [SendInterval("ATTITUDE", 30, 1e6 / 75.0, 0)]  # 50 accepted: 75
    assert r.on_ack(511, 2, 0.3) == [SendInterval("ATTITUDE", 30, 1e6 / 62.5, 0)]  # 75 refused: 62.5
    assert r.poll(0.8) == [SendInterval("ATTITUDE", 30, 1e6 / 62.5, 1)]  # no answer: resent
    assert r.poll(1.3) == [Finished({"ATTITUDE": "accepted"})]  # still none: the accepted 50 Hz stands
    assert r.granted_hz == {"ATTITUDE": 50.0}


def test_rate_requester_halves_a_refusal_down_to_the_floor():
    r = RateRequester(ack_timeout_s=0.5, max_tries=3, floor_hz=10.0)
    assert r.start([("RAW_IMU", 27, 80.0)], 0.0) == [SendInterval("RAW_IMU", 27, 12500.0, 0)]
    assert r.on_ack(511, 2, 0.1) == [SendInterval("RAW_IMU", 27, 25000.0, 0)]  # denied: 40 Hz
    assert r.on_ack(511, 4, 0.2) == [SendInterval("RAW_IMU", 27, 50000.0, 0)]  # failed: 20 Hz
    assert r.on_ack(511, 2, 0.3) == [SendInterval("RAW_IMU", 27, 100000.0, 0)]  # 10 Hz, the floor
    assert r.on_ack(511, 2, 0.4) == [Finished({"RAW_IMU": "denied"})]  # 5 Hz would be below it
    assert r.granted_hz == {} and r.asked_hz == {"RAW_IMU": 80.0}


def test_statustext_chunks_are_joined_and_a_broken_sequence_dropped():
    asm = dec.StatusTextAssembler()
    assert asm.feed("whole", 0, 0) == "whole"
    assert asm.feed("x" * 50, 3, 0) is None
    assert asm.feed("tail", 3, 1) == "x" * 50 + "tail"
    assert asm.feed("y" * 50, 4, 0) is None
    assert asm.feed("lost", 5, 1) is None  # another id mid-text, not its first chunk: dropped
    assert asm.feed("z" * 50, 6, 0) is None and asm.feed("end", 6, 1) == "z" * 50 + "end"


def test_param_value_px4_bytewise_integers_are_reinterpreted():
    m = mavlink2.MAVLink_param_value_message(b"EKF2_EV_CTRL", struct.unpack("<f", struct.pack("<i", 8))[0],
                                             mavlink2.MAV_PARAM_TYPE_INT32, 1, 0)
    assert dec.decode_param_value(m, 1.0, bytewise=True) == dec.FcParam(1.0, "EKF2_EV_CTRL", 8.0)
    a = mavlink2.MAVLink_param_value_message(b"EK2_ENABLE", 1.0, mavlink2.MAV_PARAM_TYPE_INT8, 1, 0)
    assert dec.decode_param_value(a, 1.0, bytewise=False).value == 1.0  # ArduPilot casts to float
    with pytest.raises(dec.NonFiniteField):
        dec.decode_param_value(mavlink2.MAVLink_param_value_message(b"X", float("nan"), 9, 1, 0), 1.0, False)


def test_a_1_hz_fc_attitude_is_never_a_reference_instead_of_flapping():
    """ArduPilot's stock 1 Hz ATTITUDE was fresh (< 0.5 s old) half of each second: trust, and the
    FC's heading source with it, went in and out every second. Now a stream slower than
    max_attitude_age_s is not a reference at all; 25 Hz (what a refused 50 Hz request gets) is."""
    import numpy as np
    from estimators.reference_health import health_init, health_on_attitude, health_on_ekf_status, \
        health_on_heartbeat, health_trusted
    for rate_hz, expect in ((1.0, False), (25.0, True)):
        st = health_on_ekf_status(health_on_heartbeat(health_init(), 4), True, True)
        verdicts = []
        for k in range(int(30 * rate_hz)):
            t = k / rate_hz
            st = health_on_attitude(st, np.eye(3), np.eye(3), t)
            for dt in (0.0, 0.3, 0.6 / rate_hz):  # checked at, and between, samples
                verdicts.append(health_trusted(st, t + dt))
        late = verdicts[len(verdicts) // 2:]  # after the 10 s re-trust hold and the averaging
        assert {ok for ok, _ in late} == {expect}, rate_hz
        if not expect:
            assert {why for _, why in late} == {"FC ATTITUDE every 1.00 s (> 0.5 s): too slow to be a reference"}
