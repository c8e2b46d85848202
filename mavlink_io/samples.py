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
class FcFlightState:
    """The FC's own armed / landed state where it says so: MAVLink EXTENDED_SYS_STATE.landed_state,
    a PX4 log's vehicle_status / vehicle_land_detected, an ArduPilot log's ARM/EV records. Evidence
    for the phases (take-off, started in flight); never a truth label. None = not said."""
    time_fc_s: float | None
    time_rx_s: float
    armed: bool | None
    landed: bool | None
    """True on the ground, False in the air (taking off and landing count as in the air)."""
    source: str


@dataclass(frozen=True, slots=True)
class FcEkfStatus:
    """Health of the FC's estimator (EKF_STATUS_REPORT on ArduPilot, ESTIMATOR_STATUS on PX4)."""
    time_rx_s: float
    attitude_ok: bool
    horiz_pos_ok: bool
    flags: int
    source: str
    # --- added by mavlink_io.link (optional, defaults keep the old constructor valid) -------------
    time_fc_s: float | None = None
    """FC time of the status (ESTIMATOR_STATUS carries time_usec; EKF_STATUS_REPORT has none)."""
    velocity_variance: float | None = None
    pos_horiz_variance: float | None = None
    pos_vert_variance: float | None = None
    compass_variance: float | None = None
    """Normalised innovation test ratios as the FC reports them (EKF_STATUS_REPORT variances or
    ESTIMATOR_STATUS *_ratio): < 0.5 good, > 1 rejected by the FC's own gate. Dimensionless."""


@dataclass(frozen=True, slots=True)
class FcSysStatus:
    """SYS_STATUS: onboard sensor presence and health as the FC reports it.

    The ``*_healthy`` fields are None when the sensor is not both present and enabled (a missing
    sensor is None, never "healthy")."""
    time_rx_s: float
    sensors_present: int
    sensors_enabled: int
    sensors_health: int
    gyro_healthy: bool | None
    accel_healthy: bool | None
    mag_healthy: bool | None
    baro_healthy: bool | None
    diff_pressure_healthy: bool | None
    gps_healthy: bool | None
    ahrs_healthy: bool | None
    load_fraction: float
    """Main loop load, 0..1 (SYS_STATUS.load is in d%)."""
    battery_voltage_v: float | None
    """None when the FC reports UINT16_MAX (unknown)."""
    drop_rate_comm_fraction: float


@dataclass(frozen=True, slots=True)
class CommandAck:
    """COMMAND_ACK from the autopilot addressed to us (or broadcast), for the command protocol."""
    time_rx_s: float
    command: int
    result: int
    """MAV_RESULT (0 accepted, 1 temporarily rejected, 2 denied, 3 unsupported, 4 failed,
    5 in progress, ...)."""
    progress: int
    result_param2: int
    target_system: int
    target_component: int


@dataclass(frozen=True, slots=True)
class IncomingCommand:
    """COMMAND_LONG / COMMAND_INT addressed to our component (target_system our system id,
    target_component exactly our component id), from any source (a ground station routed through
    the FC, the FC itself). Yielded after the link's signing policy; the link does not answer it
    (the command server sends COMMAND_ACK with ``link.send()``)."""
    time_rx_s: float
    command: int
    """MAV_CMD."""
    params: tuple
    """COMMAND_LONG: (p1..p7) floats; COMMAND_INT: (p1, p2, p3, p4) floats, x (int), y (int), z (float)."""
    is_int: bool
    """True when it came as COMMAND_INT."""
    frame: int | None
    """COMMAND_INT's MAV_FRAME; None for COMMAND_LONG."""
    confirmation: int
    """COMMAND_LONG's confirmation counter; 0 for COMMAND_INT."""
    source_system: int
    source_component: int
    target_system: int
    target_component: int
    signed: bool
    """True only when it carried a signature that verified with our key (False without a key)."""
