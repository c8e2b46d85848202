"""The daemon's loop blocks until input or the next timer (issue 19 item 3): it used to wake every
5 ms whatever happened. What it relies on, on a simulated clock (no wall-clock luck):

- the link never sleeps past its own timers, however long the wait it is given: our HEARTBEAT goes
  out at its 1 Hz ticks and link_lost comes at link_timeout_s, to the tick;
- the daemon's wait ends at the next MAVLink output or command try, never busy-loops on a time
  already past (a step declined it), and is LOOP_MAX_WAIT_S otherwise.
"""
from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from mavlink_io.commands import CommandProtocol, CommandSpec
from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mem_transport import MemTransport


class _Clock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


class _BlockingTransport(MemTransport):
    """Blocks as select() would: nothing arrives, so wait(t) lets t pass on the simulated clock
    (plus 1 us: a call is never free, and a link that waits 0 s at a due time must move on)."""

    def __init__(self, clock: _Clock):
        super().__init__(datagram=True)
        self.clock = clock
        self.waits: list[float] = []
        self.sent_at: list[tuple[float, bytes]] = []

    def wait(self, timeout_s):
        self.waits.append(timeout_s)
        self.clock.t += timeout_s + 1e-6

    def write(self, buf):
        self.sent_at.append((self.clock.t, bytes(buf)))
        return super().write(buf)


def _heartbeat_times(tr: _BlockingTransport) -> list[float]:
    parser = mav.MAVLink(None)
    out = []
    for t, frame in tr.sent_at:
        for m in parser.parse_buffer(frame) or []:
            if m.get_type() == "HEARTBEAT":
                out.append(t)
    return out


def test_a_long_wait_still_sends_every_heartbeat_and_finds_the_link_lost_on_time():
    # GIVEN a link that heard its autopilot at t0 and then nothing more
    clock = _Clock()
    tr = _BlockingTransport(clock)
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:9", link_timeout_s=2.0), clock=clock, transport=tr)
    t0 = clock.t
    fc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    tr.inbox.append(fc.heartbeat_encode(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4).pack(fc))
    items = link.poll(0.0)
    assert link.connected
    # WHEN the loop hands it a 10 s wait, again and again, for 5.5 s
    while clock.t < t0 + 5.5 and len(tr.waits) < 1000:
        items += link.poll(timeout_s=10.0)
    # THEN no single wait went past a timer, every HEARTBEAT left at its tick ...
    assert len(tr.waits) < 100 and max(tr.waits) <= 1.0 + 1e-9
    hb = _heartbeat_times(tr)  # (plus one at once when the peer appeared: the introduction)
    assert all(any(abs(t - (t0 + k)) < 1e-4 for t in hb) for k in range(6))
    assert max(b - a for a, b in zip(hb, hb[1:])) < 1.0 + 1e-4
    # ... and the link was declared lost at link_timeout_s after the last message, to the tick
    (lost,) = [i for i in items if isinstance(i, LinkEvent) and i.kind == "link_lost"]
    assert lost.time_rx_s == pytest.approx(t0 + 2.0, abs=1e-4)
    link.close()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    from service.config import validate
    from service.daemon import Daemon
    clock = _Clock()
    cfg = validate({"site": {"lat_deg": 47.0, "lon_deg": 8.0}, "zenoh": {"enabled": False},
                    "service": {"state_dir": str(tmp_path_factory.mktemp("state"))},
                    "azimuth": {"solve_in_background": False},
                    "outputs": {"attitude_hz": 50.0, "odometry_hz": 10.0, "named_value_hz": 2.0}})
    d = Daemon(cfg, clock=clock)
    d.test_clock = clock
    yield d
    d.pipeline.solver.close()


def test_daemon_waits_for_the_next_output_or_command_and_never_spins(daemon):
    from service.daemon import LOOP_MAX_WAIT_S
    from test_outputs_rates import solution
    d, clock = daemon, daemon.test_clock
    # GIVEN no solution yet and no command in flight: only input or the max wait wakes the loop
    d.last_solution, d.commands = None, None
    assert d.loop_wait_s() == pytest.approx(LOOP_MAX_WAIT_S)
    # WHEN a solution was sent now (ATTITUDE at 50 Hz), the first one (the FC's sample interval not
    # known yet: its next slot may have no sample of its own) THEN the loop wakes for the next output
    d.last_solution, d._last_solution_s = solution(t_fc=10.0, t_rx=clock.t), clock.t
    d.scheduler.messages(d.last_solution, clock.t)
    assert d.loop_wait_s() == pytest.approx(0.02, abs=1e-9)
    clock.t += 0.013
    assert d.loop_wait_s() == pytest.approx(0.007, abs=1e-9)
    # (the ODOMETRY slot, not allowed yet, was taken by that solution: no reason to wake, no spin)
    # WHEN that output time passed and the step declined it (no fresh solution) THEN no busy loop
    clock.t += 0.5
    assert d.loop_wait_s() == pytest.approx(LOOP_MAX_WAIT_S)
    # WHEN the FC's samples come every 2.5 ms (denser than the slots) THEN each slot is sent as its
    # sample is handled: no output wakes the loop, only input
    for k in (1, 2):
        d.last_solution, d._last_solution_s = solution(t_fc=10.5 + k * 0.0025, t_rx=clock.t), clock.t
        d.scheduler.messages(d.last_solution, clock.t)
    assert d.scheduler.next_fill_s() is None and d.loop_wait_s() == pytest.approx(LOOP_MAX_WAIT_S)
    # WHEN they come every 40 ms (25 Hz, sparser than the 50 Hz slots) THEN the loop wakes for the slot
    # between two samples, at its FC time carried to the local clock
    d.last_solution, d._last_solution_s = solution(t_fc=10.5475, t_rx=clock.t), clock.t
    d.scheduler.messages(d.last_solution, clock.t)
    assert d.loop_wait_s() == pytest.approx(10.56 - 10.5475, abs=1e-9)
    # WHEN a command was sent and waits for its ACK THEN the loop wakes for its retry
    d.last_solution = None
    sent = []
    d.commands = CommandProtocol(sent.append, lambda: (1, 1))
    d.commands.submit(CommandSpec("rtl", mav.MAV_CMD_NAV_RETURN_TO_LAUNCH), clock.t)
    assert len(sent) == 1
    assert d.loop_wait_s() == pytest.approx(min(LOOP_MAX_WAIT_S, d.commands.params.ack_timeout_s), abs=1e-9)
    clock.t += d.commands.params.ack_timeout_s - 0.03
    assert d.loop_wait_s() == pytest.approx(0.03, abs=1e-9)
    # a command that cannot be sent (no autopilot known yet) is declined by its step: no spin
    d.commands = CommandProtocol(sent.append, lambda: (None, None))
    d.commands.submit(CommandSpec("rtl", mav.MAV_CMD_NAV_RETURN_TO_LAUNCH), clock.t)
    d.commands.poll(clock.t)
    assert d.loop_wait_s() == pytest.approx(LOOP_MAX_WAIT_S)
    d.commands = None
