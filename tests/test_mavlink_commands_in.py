"""Commands addressed to our component (COMMAND_LONG / COMMAND_INT from a ground station routed by
the FC, or from the FC) come out of the link as IncomingCommand; broadcasts are counted, not yielded."""
from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.link import LinkConfig, MavlinkLink
from mavlink_io.samples import ImuSample, IncomingCommand
from mavlink_io.transport import NullTransport

US = 191


def make_link(system_id=None):
    return MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", system_id=system_id), clock=lambda: 5.0,
                       transport=NullTransport(None))


def pack(mav, msg) -> bytes:
    buf = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return buf


FC = mavlink2.MAVLink(None, srcSystem=42, srcComponent=1)
GCS = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)


def fc_heartbeat() -> bytes:
    return pack(FC, mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_FIXED_WING,
                                                       mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3))


def commands(items):
    return [i for i in items if isinstance(i, IncomingCommand)]


def test_command_long_from_a_gcs_is_decoded():
    link = make_link()
    link.feed(fc_heartbeat())  # we learn the vehicle's system id (42)
    msg = mavlink2.MAVLink_command_long_message(42, US, mavlink2.MAV_CMD_REQUEST_MESSAGE, 3,
                                                331.0, -2.5, 0.0, float("nan"), 1e6, -7.25, 0.125)
    items = link.feed(pack(GCS, msg), rx_s=12.5)
    (c,) = commands(items)
    assert (c.command, c.is_int, c.frame, c.confirmation) == (mavlink2.MAV_CMD_REQUEST_MESSAGE, False, None, 3)
    assert (c.source_system, c.source_component, c.target_system, c.target_component) == (255, 190, 42, US)
    assert c.params[:3] == (331.0, -2.5, 0.0) and math.isnan(c.params[3]) and c.params[4:] == (1e6, -7.25, 0.125)
    assert len(c.params) == 7 and c.time_rx_s == 12.5 and c.signed is False
    assert link.stats.commands_received == 1 and link.stats.foreign_messages == 0


def test_command_int_from_a_gcs_is_decoded():
    link = make_link(system_id=42)
    msg = mavlink2.MAVLink_command_int_message(42, US, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                               mavlink2.MAV_CMD_DO_REPOSITION, 0, 0, -1.0, 1.0, 0.0, float("nan"),
                                               473_977_418, 85_455_939, 120.5)
    (c,) = commands(link.feed(pack(GCS, msg)))
    assert (c.command, c.is_int, c.frame, c.confirmation) == (mavlink2.MAV_CMD_DO_REPOSITION, True,
                                                              mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0)
    assert c.params[:3] == (-1.0, 1.0, 0.0) and math.isnan(c.params[3])
    assert c.params[4:] == (473_977_418, 85_455_939, 120.5)
    assert isinstance(c.params[4], int) and isinstance(c.params[5], int) and isinstance(c.params[6], float)
    assert (c.source_system, c.source_component) == (255, 190)


def test_broadcast_and_other_targets_are_not_yielded():
    link = make_link(system_id=42)
    frames = b"".join(pack(GCS, mavlink2.MAVLink_command_long_message(ts, tc, 400, 0, 1, 0, 0, 0, 0, 0, 0))
                      for ts, tc in ((42, 0), (0, 0), (0, US), (42, 1), (7, US)))
    assert commands(link.feed(frames)) == []
    assert link.stats.commands_broadcast_ignored == 3  # (42, 0), (0, 0), (0, 191)
    assert link.stats.commands_received == 0
    assert link.stats.foreign_messages == 2  # for the FC's component, for another vehicle


def test_command_from_the_fc_itself_is_yielded_and_its_stream_still_counted():
    link = make_link()
    link.feed(fc_heartbeat())
    imu = mavlink2.MAVLink_raw_imu_message(1_000_000, 1, 2, -1000, 3, 4, 5, 200, 10, 400, 0, 0)
    cmd = mavlink2.MAVLink_command_long_message(42, US, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    items = link.feed(pack(FC, cmd) + pack(FC, imu))
    assert len(commands(items)) == 1 and commands(items)[0].source_system == 42
    assert sum(isinstance(i, ImuSample) for i in items) == 1
    assert link.stats.seq_lost == 0 and link.stats.messages_by_type.get("COMMAND_LONG") == 1
