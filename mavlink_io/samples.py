"""Typed samples decoded from MAVLink, in SI units, with both clocks.

Every sample carries ``time_fc_s`` (the flight controller's clock: time_usec or time_boot_ms,
converted to seconds, used by the estimators to integrate) and ``time_rx_s`` (local monotonic
receive time, used for latency, link health and timeouts). Vectors are numpy arrays of shape (3,)
in the IMU sensor frame (FRD as the FC reports it). A missing sensor is ``None``, never zeros.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class ImuSample:
    time_fc_s: float
    time_rx_s: float
    gyro_rad_s: np.ndarray
    """Angular rate, rad/s, sensor axes."""
    accel_m_s2: np.ndarray
    """Specific force, m/s^2, sensor axes (at rest and level: [0, 0, -g])."""
    mag_gauss: np.ndarray | None
    """Magnetic field, gauss, sensor axes; None when the message carried none."""
    source: str
    """The MAVLink message it came from: RAW_IMU, HIGHRES_IMU, SCALED_IMU."""
    imu_id: int = 0


@dataclass(frozen=True, slots=True)
class PressureSample:
    time_fc_s: float
    time_rx_s: float
    press_abs_pa: float
    press_diff_pa: float | None
    """Differential (pitot) pressure; None when the FC has no airspeed sensor."""
    temperature_k: float | None
    source: str = "SCALED_PRESSURE"


@dataclass(frozen=True, slots=True)
class FcAttitude:
    """The flight controller's own attitude estimate (ATTITUDE)."""
    time_fc_s: float
    time_rx_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    """Yaw as the FC sends it, in (-pi, pi]."""
    rates_rad_s: np.ndarray


@dataclass(frozen=True, slots=True)
class FcHeartbeat:
    time_rx_s: float
    system_id: int
    component_id: int
    autopilot: str
    """"ardupilot", "px4" or "other"."""
    vehicle_type: int
    base_mode: int
    custom_mode: int
    system_status: int
    armed: bool


@dataclass(frozen=True, slots=True)
class FcEkfStatus:
    """Health of the FC's estimator (EKF_STATUS_REPORT on ArduPilot, ESTIMATOR_STATUS on PX4)."""
    time_rx_s: float
    attitude_ok: bool
    horiz_pos_ok: bool
    flags: int
    source: str
