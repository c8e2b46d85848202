"""Commands to our component: the decision for each command, retries answered once."""
from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as m

from mavlink_io.samples import IncomingCommand
from service.command_server import CommandServer


def cmd(command: int, p1: float = 0.0, confirmation: int = 0, is_int: bool = False, src=(255, 190),
        signed: bool = True) -> IncomingCommand:
    params = (p1, 0.0, 0.0, 0.0, 0, 0, 0.0) if is_int else (p1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return IncomingCommand(time_rx_s=0.0, command=command, params=params, is_int=is_int,
                           frame=0 if is_int else None, confirmation=confirmation, source_system=src[0],
                           source_component=src[1], target_system=1, target_component=191, signed=signed)


def test_request_message():
    s = CommandServer(accept_commands=True, fence_configured=False)
    d = s.decide(cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_ATTITUDE), 0.0, have_solution=True)
    assert (d.result, d.action, d.message_id) == (m.MAV_RESULT_ACCEPTED, "request_message", 30)
    d = s.decide(cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_ATTITUDE, src=(255, 191)), 0.0, have_solution=False)
    assert d.result == m.MAV_RESULT_TEMPORARILY_REJECTED and d.action is None
    d = s.decide(cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_HEARTBEAT, src=(255, 192)), 0.0, have_solution=False)
    assert d.result == m.MAV_RESULT_ACCEPTED  # a heartbeat needs no solution
    for bad in (m.MAVLINK_MSG_ID_GPS_RAW_INT, 30.5, math.nan, -1.0):
        d = s.decide(cmd(m.MAV_CMD_REQUEST_MESSAGE, bad, src=(250, 1)), 0.0, have_solution=True)
        assert d.result == m.MAV_RESULT_DENIED and d.action is None, bad


def test_fence_enable_disable_and_unsupported_values():
    s = CommandServer(accept_commands=True, fence_configured=True)
    d = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 0.0), 0.0, True)
    assert (d.result, d.action) == (m.MAV_RESULT_ACCEPTED, "fence_disable")
    assert "DISABLED" in d.reason and "255/190" in d.reason and "signed" in d.reason
    d = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 1.0, src=(255, 1)), 0.0, True)
    assert (d.result, d.action) == (m.MAV_RESULT_ACCEPTED, "fence_enable")
    d = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 2.0, src=(255, 2)), 0.0, True)
    assert d.result == m.MAV_RESULT_UNSUPPORTED and d.action is None
    nofence = CommandServer(accept_commands=True, fence_configured=False)
    assert nofence.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 0.0), 0.0, True).result == m.MAV_RESULT_DENIED


def test_unknown_commands_are_unsupported_and_accept_commands_false_denies_all():
    s = CommandServer(accept_commands=True, fence_configured=True)
    d = s.decide(cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), 0.0, True)
    assert d.result == m.MAV_RESULT_UNSUPPORTED and "MAV_CMD_COMPONENT_ARM_DISARM" in d.reason
    off = CommandServer(accept_commands=False, fence_configured=True)
    for c in (m.MAV_CMD_REQUEST_MESSAGE, m.MAV_CMD_DO_FENCE_ENABLE, 31000):
        d = off.decide(cmd(c, 0.0), 0.0, True)
        assert d.result == m.MAV_RESULT_DENIED and d.action is None
    assert off.counts == {"DENIED": 3}


def test_a_retry_is_answered_with_the_first_answer_and_not_acted_on_again():
    s = CommandServer(accept_commands=True, fence_configured=True)
    first = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 0.0), 10.0, True)
    retry = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 0.0, confirmation=1), 10.4, True)
    assert retry.repeat and retry.result == first.result and retry.action is None
    # a new command (confirmation 0) is acted on again; so is a retry after the window
    again = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 0.0), 11.0, True)
    assert not again.repeat and again.action == "fence_disable"
    late = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 0.0, confirmation=2), 30.0, True)
    assert not late.repeat and late.action == "fence_disable"
    # different parameters or another source: not a retry
    other = s.decide(cmd(m.MAV_CMD_DO_FENCE_ENABLE, 1.0, confirmation=1), 30.1, True)
    assert not other.repeat and other.action == "fence_enable"


def test_revise_changes_the_answer_for_later_retries_too():
    s = CommandServer(accept_commands=True, fence_configured=False)
    d = s.decide(cmd(m.MAV_CMD_REQUEST_MESSAGE, 31.0), 0.0, True)
    d2 = s.revise(d, m.MAV_RESULT_TEMPORARILY_REJECTED, "not available now")
    assert d2.result == m.MAV_RESULT_TEMPORARILY_REJECTED and d2.action is None
    retry = s.decide(cmd(m.MAV_CMD_REQUEST_MESSAGE, 31.0, confirmation=1), 0.5, True)
    assert retry.repeat and retry.result == m.MAV_RESULT_TEMPORARILY_REJECTED
    assert s.counts == {"ACCEPTED": 0, "TEMPORARILY_REJECTED": 2}
