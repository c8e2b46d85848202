"""The daemon's navigation solution: one snapshot per IMU sample, what every output publishes.

Publishers (MAVLink out, Zenoh, the status line) read this and nothing else from the estimators.
Angles in radians; sigmas are 1-sigma; None where the quantity is not (yet) available.

It lives in mavlink_io because both sides need it and the layering allows only one direction:
service (the Pipeline that builds it, Zenoh, the daemon) imports mavlink_io, whose encoders read it;
mavlink_io imports nothing of service. numpy is its only dependency.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, slots=True)
class NavSolution:
    time_fc_s: float
    """FC time of the IMU sample this solution is for (s)."""
    time_rx_s: float
    """Local monotonic time that sample was received (s)."""
    phase: str
    """boot | pre-launch | launch | in-flight."""
    q_nav_from_body: np.ndarray | None
    """Best attitude, Hamilton [w, x, y, z]; yaw part only meaningful when heading_valid."""
    roll_rad: float | None
    pitch_rad: float | None
    rates_body_rad_s: np.ndarray | None
    roll_sigma_rad: float | None = None
    pitch_sigma_rad: float | None = None
    heading_rad: float | None = None
    """True heading of the body x axis, [0, 2pi)."""
    heading_sigma_rad: float | None = None
    heading_source: str = "none"
    """azimuth | synthetic_ahrs | heading_filter | fc | none."""
    heading_valid: bool = False
    azimuth_rad: float | None = None
    """Flight azimuth from method A, [0, 2pi)."""
    azimuth_sigma_rad: float | None = None
    flags: dict = field(default_factory=dict)
    """Estimator flags a user should see (e.g. {"azimuth_gate": "orientation diversity 2.1 deg"})."""
