"""The compiled core's half of the MAVLink link: what the service hands MavlinkLink (mavlink_io imports
nothing above it, so it cannot pick the core itself).

:func:`frame_scan`: estimators._core.split_raw_imu (core/mavlink_frames.hpp, core/bindings_link.cpp) bound
to mavlink_io.frame_scan.RawImuFrame: mavlink_io.frame_scan.split_raw_imu in C++ (the read walked frame by
frame with pymavlink's framing rules, CRC-16/MCRF4XX with RAW_IMU's CRC_EXTRA, the unsigned RAW_IMU frames
set apart; tests/test_link_core.py holds the two equal). None when ``AZIMUTHD_CORE=python``, when the core
is not built or was built before it: the link then runs the Python scan.
"""
from __future__ import annotations

import functools
import os
from typing import Callable

from mavlink_io.frame_scan import RawImuFrame
from service.core_backend import ENV


def frame_scan(environ=os.environ) -> Callable | None:
    """The core's split_raw_imu(data) for ``MavlinkLink(frame_scan=...)``, or None (the Python scan)."""
    if environ.get(ENV, "").strip().lower() == "python":
        return None
    try:
        from estimators import _core
    except ImportError:
        return None
    fn = getattr(_core, "split_raw_imu", None)
    return None if fn is None else functools.partial(fn, RawImuFrame)   # fn(frame_type, data): no Python frame
