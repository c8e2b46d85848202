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
    from mavlink_io.link import MavlinkLink
    items = []
    msg = mav.MAVLink_extended_sys_state_message(vtol_state=0, landed_state=2)
    MavlinkLink._decode(object.__new__(MavlinkLink), "EXTENDED_SYS_STATE", msg, 3.0, items)
    assert items == [FcFlightState(None, 3.0, None, False, "EXTENDED_SYS_STATE")]
