"""mavlink_io/commands.py: the command protocol against fake peers (direct calls and loopback UDP)."""
import math
import os
import socket
import threading
import time

os.environ["MAVLINK20"] = "1"

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.commands import (CommandProtocol, CommandProtocolParams, CommandSpec, cmd_reposition, cmd_rtl,
                                 cmd_set_mode, cmd_terminate, statustext_message)
from mavlink_io.samples import CommandAck

P = CommandProtocolParams(ack_timeout_s=1.0, max_tries=4, in_progress_timeout_s=5.0, max_queue=3,
                          min_send_interval_s=0.05)


class Peer:
    """Collects what the protocol sends; the test decides what to answer."""

    def __init__(self):
        self.sent = []

    def send(self, msg):
        self.sent.append(msg)


def ack(command, result, t=0.0):
    return CommandAck(t, command, result, 0, 0, 1, 191)


def make(params=P, target=(1, 1)):
    peer = Peer()
    outcomes = []
    proto = CommandProtocol(peer.send, lambda: target, params, on_outcome=outcomes.append)
    return proto, peer, outcomes


def test_first_ack_dropped_retry_with_confirmation_then_accepted():
    proto, peer, outcomes = make()
    proto.submit(cmd_rtl(), 0.0)
    assert len(peer.sent) == 1 and peer.sent[0].confirmation == 0
    assert proto.poll(0.99) == [] and len(peer.sent) == 1      # still waiting for the ACK
    proto.poll(1.0)                                             # timeout: retry
    assert len(peer.sent) == 2 and peer.sent[1].confirmation == 1
    assert peer.sent[1].command == mavlink2.MAV_CMD_NAV_RETURN_TO_LAUNCH
    out = proto.on_command_ack(ack(20, 0), 1.2)                 # the peer ACKs the retry
    assert [(o.status, o.result, o.tries) for o in out] == [("accepted", 0, 2)]
    assert out[0].finished_s - out[0].submitted_s == pytest.approx(1.2)
    assert outcomes == out and proto.idle
    proto.poll(10.0)
    assert len(peer.sent) == 2                                  # nothing more after the outcome


def test_peer_that_never_answers_times_out_after_n_tries():
    proto, peer, outcomes = make()
    proto.submit(cmd_rtl(), 0.0)
    t = 0.0
    while t < 20.0:
        t += 0.01
        proto.poll(t)
    assert [m.confirmation for m in peer.sent] == [0, 1, 2, 3]  # exactly max_tries sends, no flood
    assert len(outcomes) == 1
    o = outcomes[0]
    assert (o.status, o.result, o.tries) == ("timeout", None, 4)
    assert o.finished_s == pytest.approx(4.0, abs=0.041)        # 4 tries x 1 s (+ one 10 ms poll step each)
    assert proto.stats.retries == 3


def test_a_late_reader_waits_its_input_delay_before_a_retry():
    # GIVEN a caller reading its input 30 s late (the geofence monitor's input age) and an FC that
    # ACKs at once: the ACK reaches the caller 30 s after it was sent
    proto, peer, outcomes = make()
    proto.input_delay_s = 30.0
    proto.submit(cmd_rtl(), 0.0)
    # WHEN the ACK timeout (1 s) has passed but not the delay on top of it
    t = 0.0
    while t < 30.9:
        t += 0.1
        proto.poll(t)
    # THEN nothing was resent and nothing timed out (no escalation on an ACK not yet read) ...
    assert len(peer.sent) == 1 and outcomes == [] and proto.next_due_s() == pytest.approx(31.0)
    out = proto.on_command_ack(ack(20, 0), 30.95)
    assert [(o.status, o.tries) for o in out] == [("accepted", 1)]
    # ... and with no ACK at all, the tries still run out: 4 x (1 + 30) s
    proto2, peer2, outcomes2 = make()
    proto2.input_delay_s = 30.0
    proto2.submit(cmd_rtl(), 0.0)
    t = 0.0
    while t < 130.0:
        t += 0.1
        proto2.poll(t)
    assert len(peer2.sent) == 4 and [(o.status, o.tries) for o in outcomes2] == [("timeout", 4)]
    assert outcomes2[0].finished_s == pytest.approx(124.0, abs=0.41)  # (+ one 0.1 s poll step each)


def test_denied_and_unsupported_are_final_with_the_result():
    proto, peer, outcomes = make()
    proto.submit(cmd_rtl(), 0.0)
    out = proto.on_command_ack(ack(20, mavlink2.MAV_RESULT_UNSUPPORTED), 0.1)
    assert [(o.status, o.result_name) for o in out] == [("denied", "unsupported")]
    proto.poll(5.0)
    assert len(peer.sent) == 1


def test_in_progress_waits_without_resending_then_final_ack():
    proto, peer, outcomes = make()
    proto.submit(cmd_rtl(), 0.0)
    assert proto.on_command_ack(ack(20, mavlink2.MAV_RESULT_IN_PROGRESS), 0.2) == []
    for t in (1.0, 2.0, 4.0, 5.1):
        assert proto.poll(t) == []
    assert len(peer.sent) == 1                                  # no resend while in progress
    out = proto.on_command_ack(ack(20, 0), 5.15)
    assert [o.status for o in out] == ["accepted"]


def test_in_progress_without_final_ack_times_out():
    proto, peer, outcomes = make()
    proto.submit(cmd_rtl(), 0.0)
    proto.on_command_ack(ack(20, mavlink2.MAV_RESULT_IN_PROGRESS), 0.2)
    assert proto.poll(5.19) == []
    out = proto.poll(5.21)
    assert [(o.status, o.detail) for o in out] == [("timeout", "no final ACK after IN_PROGRESS")]
    assert len(peer.sent) == 1


def test_temporarily_rejected_is_retried_at_the_timeout_not_at_once():
    proto, peer, outcomes = make()
    proto.submit(cmd_rtl(), 0.0)
    proto.on_command_ack(ack(20, mavlink2.MAV_RESULT_TEMPORARILY_REJECTED), 0.1)
    proto.poll(0.5)
    assert len(peer.sent) == 1
    proto.poll(1.1)
    assert len(peer.sent) == 2 and peer.sent[1].confirmation == 1
    for k in range(2, 4):
        proto.on_command_ack(ack(20, mavlink2.MAV_RESULT_TEMPORARILY_REJECTED), k + 0.0)
        proto.poll(k + 1.01)
    assert len(peer.sent) == 4
    out = proto.on_command_ack(ack(20, mavlink2.MAV_RESULT_TEMPORARILY_REJECTED), 4.1)
    assert [(o.status, o.result_name, o.tries) for o in out] == [("denied", "temporarily_rejected", 4)]


def test_one_command_in_flight_queue_and_dedup():
    proto, peer, outcomes = make()
    a = cmd_rtl()
    b = cmd_set_mode("rtl", "ardupilot", 1)
    proto.submit(a, 0.0)
    proto.submit(b, 0.0)
    proto.submit(cmd_rtl(), 0.1)            # equal to the one in flight: ignored
    proto.submit(cmd_set_mode("rtl", "ardupilot", 1), 0.1)  # equal to a queued one: ignored
    assert len(peer.sent) == 1 and proto.pending == [b]
    proto.poll(0.5)
    assert len(peer.sent) == 1              # b waits for a
    proto.on_command_ack(ack(176, 0), 0.6)  # an ACK for another command: not ours
    assert proto.in_flight == a and proto.stats.acks_unmatched == 1
    out = proto.on_command_ack(ack(20, 0), 0.7)
    assert [o.name for o in out] == ["rtl"]
    assert len(peer.sent) == 2 and peer.sent[1].command == 176  # b sent as soon as a finished
    assert peer.sent[1].param1 == 1 and peer.sent[1].param2 == 11  # custom mode, ArduPlane RTL


def test_full_queue_drops_the_oldest_and_supersede_cancels_everything():
    proto, peer, outcomes = make()
    proto.submit(cmd_rtl(), 0.0)
    specs = [CommandSpec(f"c{i}", 31000 + i) for i in range(4)]
    for s in specs:
        proto.submit(s, 0.1)
    assert [o.name for o in outcomes] == ["c0"] and outcomes[0].status == "superseded"
    assert [s.name for s in proto.pending] == ["c1", "c2", "c3"]
    out = proto.submit(cmd_terminate(), 0.2, supersede=True)
    assert [(o.name, o.status) for o in out] == [("rtl", "superseded"), ("c1", "superseded"),
                                                 ("c2", "superseded"), ("c3", "superseded")]
    assert proto.in_flight.name == "terminate"
    assert peer.sent[-1].command == mavlink2.MAV_CMD_DO_FLIGHTTERMINATION and peer.sent[-1].param1 == 1


def test_command_int_reposition_encoding_and_resend_unchanged():
    proto, peer, _ = make()
    proto.submit(cmd_reposition(47.123456789, -8.5, 120.0), 0.0)
    m = peer.sent[0]
    assert m.get_type() == "COMMAND_INT" and m.command == mavlink2.MAV_CMD_DO_REPOSITION
    assert (m.x, m.y, m.z) == (471234568, -85000000, 120.0)
    assert m.frame == mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and m.param1 == -1 and math.isnan(m.param4)
    proto.poll(1.0)
    assert len(peer.sent) == 2 and peer.sent[1].get_msgbuf()[10:] == m.get_msgbuf()[10:]  # same payload
    proto.submit(cmd_reposition(47.123456789, -8.5, 120.0), 1.1)  # NaN param4: still de-duplicated
    assert proto.pending == []


def test_nothing_is_sent_before_the_autopilot_is_known():
    target = [None, None]
    peer = Peer()
    proto = CommandProtocol(peer.send, lambda: tuple(target), P)
    proto.submit(cmd_rtl(), 0.0)
    proto.poll(3.0)
    assert peer.sent == []
    target[:] = [1, 1]
    proto.poll(3.1)
    assert len(peer.sent) == 1 and peer.sent[0].confirmation == 0 and peer.sent[0].target_system == 1


def test_set_mode_per_autopilot_and_statustext():
    px4 = cmd_set_mode("rtl", "px4", 1)
    assert px4.params[:3] == (1.0, 4.0, 5.0)
    copter = cmd_set_mode("rtl", "ardupilot", 2)
    assert copter.params[1] == 6.0
    st = statustext_message("critical", "x" * 80)
    assert st.severity == 2 and len(st.text) == 50
    with pytest.raises(ValueError, match="params"):
        CommandSpec("bad", 20, (0.0,) * 6)


class UdpFakeAutopilot(threading.Thread):
    """A pymavlink peer on loopback UDP that drops the first COMMAND_LONG (no ACK) or never answers."""

    def __init__(self, drop_first: bool, answer: bool):
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        self.rx = mavlink2.MAVLink(None)
        self.drop_first, self.answer = drop_first, answer
        self.received = []
        self.stop = threading.Event()

    def run(self):
        while not self.stop.is_set():
            try:
                data, addr = self.sock.recvfrom(4096)
            except (socket.timeout, TimeoutError):
                continue
            for msg in self.rx.parse_buffer(data) or []:
                if msg.get_type() != "COMMAND_LONG":
                    continue
                self.received.append(msg)
                if not self.answer or (self.drop_first and len(self.received) == 1):
                    continue
                out = self.mav.command_ack_encode(msg.command, 0, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
                self.sock.sendto(out.pack(self.mav), addr)


@pytest.mark.parametrize("drop_first, answer, status, tries", [(True, True, "accepted", 2), (False, False, "timeout", 3)])
def test_loopback_udp_peer(drop_first, answer, status, tries):
    peer = UdpFakeAutopilot(drop_first, answer)
    peer.start()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.01)
    ours = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    rx = mavlink2.MAVLink(None)
    proto = CommandProtocol(lambda m: sock.sendto(m.pack(ours), ("127.0.0.1", peer.port)), lambda: (1, 1),
                            CommandProtocolParams(ack_timeout_s=0.2, max_tries=3))
    outcomes = []
    try:
        proto.submit(cmd_rtl(), time.monotonic())
        t_end = time.monotonic() + 3.0
        while not outcomes and time.monotonic() < t_end:
            try:
                data = sock.recv(4096)
                for m in rx.parse_buffer(data) or []:
                    if m.get_type() == "COMMAND_ACK":
                        outcomes += proto.on_command_ack(m, time.monotonic())
            except (socket.timeout, TimeoutError):
                pass
            outcomes += proto.poll(time.monotonic())
    finally:
        peer.stop.set()
        peer.join(1.0)
        sock.close()
        peer.sock.close()
    assert [(o.status, o.tries) for o in outcomes] == [(status, tries)]
    assert [m.confirmation for m in peer.received] == list(range(tries))
