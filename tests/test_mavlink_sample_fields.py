"""The link stamps each IMU, pressure and attitude sample with its FC time by rebuilding it
(mavlink_io/sample_decoder.py: cheaper than dataclasses.replace at the input rates). Every other
field must come through untouched: GIVEN frames fed through a link WHEN a sample comes out THEN it
equals, field by field, the pure decode of the same message with the FC time replaced (a field added
to samples.py and not to the rebuild fails here)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from mavlink_io import decode as dec
from mavlink_io.link import LinkConfig, MavlinkLink
from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
from mavlink_io.transport import NullTransport
from mavlink_io.url import parse_url


def _same(a, b) -> bool:
    if type(a) is not type(b):
        return False
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (isinstance(x, np.ndarray) and isinstance(y, np.ndarray) and np.array_equal(x, y)):
                return False
        elif not (x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))):
            return False
    return True


def test_stamped_samples_keep_every_field():
    url = "udpin:127.0.0.1:9"
    link = MavlinkLink(LinkConfig(url=url, imu_id=2), clock=lambda: 5.0, transport=NullTransport(parse_url(url)))
    fc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    link.feed(fc.heartbeat_encode(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4).pack(fc), rx_s=4.0)
    msgs = [fc.raw_imu_encode(3_000_000, 12, -7, -990, 3, -4, 5, 210, -35, 420, 2, 3100),
            fc.scaled_pressure_encode(3000, 1009.25, 0.75, 2150, 0),
            fc.attitude_encode(3000, 0.1, -0.2, 1.3, 0.01, -0.02, 0.03)]
    frames = [m.pack(fc) for m in msgs]
    wire = [mav.MAVLink(None).parse_char(f) for f in frames]  # as received (float32 fields)
    ref = {ImuSample: dec.decode_raw_imu(wire[0], math.nan, 5.0),
           PressureSample: dec.decode_scaled_pressure(wire[1], math.nan, 5.0),
           FcAttitude: dec.decode_attitude(wire[2], math.nan, 5.0)}
    out = [i for f in frames for i in link.feed(f, rx_s=5.0) if type(i) in ref]
    assert [type(i) for i in out] == [ImuSample, PressureSample, FcAttitude]
    for item in out:
        assert item.time_fc_s == 3.0
        assert _same(item, dataclasses.replace(ref[type(item)], time_fc_s=item.time_fc_s)), item
