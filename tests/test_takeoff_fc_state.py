"""The FC's own landed state on the wire: MAVLink EXTENDED_SYS_STATE -> FcFlightState.

GIVEN EXTENDED_SYS_STATE messages built with pymavlink WHEN decoded THEN ON_GROUND is landed,
IN_AIR / TAKEOFF / LANDING are in the air, UNDEFINED and values outside the enum say nothing;
and the link hands the decoded state on (what the daemon gives Pipeline.on_fc_flight_state).
"""
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from mavlink_io.decode import decode_extended_sys_state
from mavlink_io.samples import FcFlightState


@pytest.mark.parametrize("landed_state, landed", [(0, None), (1, True), (2, False), (3, False), (4, False),
                                                   (9, None)])
def test_landed_state_decoded(landed_state, landed):
    msg = mav.MAVLink_extended_sys_state_message(vtol_state=0, landed_state=landed_state)
    st = decode_extended_sys_state(msg, 12.5)
    assert st == FcFlightState(None, 12.5, None, landed, "EXTENDED_SYS_STATE")


def test_the_link_hands_it_on():
    from mavlink_io.link import LinkConfig, MavlinkLink
    from mavlink_io.transport import NullTransport
    from mavlink_io.url import parse_url
    # GIVEN a link that knows its autopilot (system 1, component 1)
    url = "udpin:127.0.0.1:9"
    link = MavlinkLink(LinkConfig(url=url), clock=lambda: 3.0, transport=NullTransport(parse_url(url)))
    fc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    link.feed(fc.heartbeat_encode(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0).pack(fc),
              rx_s=2.0)
    # WHEN its EXTENDED_SYS_STATE arrives
    msg = mav.MAVLink_extended_sys_state_message(vtol_state=0, landed_state=2)
    items = link.feed(msg.pack(fc), rx_s=3.0)
    # THEN the decoded state comes out as it is
    assert [i for i in items if isinstance(i, FcFlightState)] == [
        FcFlightState(None, 3.0, None, False, "EXTENDED_SYS_STATE")]
