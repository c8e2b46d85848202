"""MAVLink messages -> typed samples in SI units (mavlink_io.samples). Pure functions.

Unit conversions (MAVLink common.xml / ardupilotmega.xml field units):

=================  =====================================  ====================================
message            wire units                             sample units
=================  =====================================  ====================================
RAW_IMU            acc mG, gyro mrad/s, mag mgauss        m/s^2 (x 1e-3 g0), rad/s, gauss
SCALED_IMU         acc mG, gyro mrad/s, mag mgauss        idem
HIGHRES_IMU        m/s^2, rad/s, gauss, hPa, degC         m/s^2, rad/s, gauss, Pa (x 100), K
SCALED_PRESSURE    press_abs/diff hPa, temperature cdegC  Pa (x 100), K (x 0.01 + 273.15)
ATTITUDE           rad, rad/s                             rad, rad/s
=================  =====================================  ====================================

g0 = 9.80665 m/s^2 (the standard gravity ArduPilot uses to scale its mG: GRAVITY_MSS).
A RAW_IMU/SCALED_IMU magnetometer of exactly (0, 0, 0) means "no compass" (the FC fills zeros):
it becomes ``mag_gauss=None``. HIGHRES_IMU fields count only when their ``fields_updated`` bit is
set (a sender that leaves fields_updated at 0 is taken to have filled every field).

Required fields that are not finite raise :class:`NonFiniteField` (the link counts it and hands
on nothing); non-finite optional fields (mag, differential pressure, temperature, variances)
become None and are counted in an :class:`OptionalFieldCounter` passed by the caller.
Timestamps are integers, converted by mavlink_io.timebase; the decoders here take ``time_fc_s``
already computed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mavlink_io.samples import (CommandAck, FcAttitude, FcEkfStatus, FcFlightState, FcHeartbeat, FcSysStatus,
                                ImuSample, PressureSample)

G0_M_S2 = 9.80665
"""Standard gravity, m/s^2: 1 mG = 1e-3 * G0_M_S2 m/s^2."""
MG_TO_M_S2 = 1e-3 * G0_M_S2
MRAD_TO_RAD = 1e-3
MGAUSS_TO_GAUSS = 1e-3
HPA_TO_PA = 100.0
CDEGC_TO_DEGC = 0.01
ZERO_CELSIUS_K = 273.15

AUTOPILOT_ARDUPILOT = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
AUTOPILOT_PX4 = 12  # MAV_AUTOPILOT_PX4
MODE_FLAG_SAFETY_ARMED = 128

# HIGHRES_IMU.fields_updated bits
HR_ACC = 0x7
HR_GYRO = 0x38
HR_MAG = 0x1C0
HR_ABS_PRESSURE = 0x200
HR_DIFF_PRESSURE = 0x400
HR_TEMPERATURE = 0x1000

# SYS_STATUS sensor bits (MAV_SYS_STATUS_SENSOR)
SENSOR_GYRO = 1
SENSOR_ACCEL = 2
SENSOR_MAG = 4
SENSOR_ABS_PRESSURE = 8
SENSOR_DIFF_PRESSURE = 16
SENSOR_GPS = 32
SENSOR_AHRS = 0x200000

# EKF_STATUS_REPORT / ESTIMATOR_STATUS flags (same bit layout for the two we use)
EST_ATTITUDE = 1
EST_POS_HORIZ_ABS = 16
EKF_UNINITIALIZED = 1024

# time field and unit per stamped message: ("time_usec", "us") or ("time_boot_ms", "ms")
TIME_FIELD = {
    "RAW_IMU": ("time_usec", "us"),
    "HIGHRES_IMU": ("time_usec", "us"),
    "SCALED_IMU": ("time_boot_ms", "ms"),
    "SCALED_PRESSURE": ("time_boot_ms", "ms"),
    "ATTITUDE": ("time_boot_ms", "ms"),
    "ESTIMATOR_STATUS": ("time_usec", "us"),
}


class NonFiniteField(ValueError):
    """A required field was NaN or infinite: the whole sample is rejected."""

    def __init__(self, msg_type: str, field: str, value: float):
        super().__init__(f"{msg_type}.{field} is not finite ({value!r})")
        self.msg_type = msg_type
        self.field = field


def autopilot_name(autopilot: int) -> str:
    """HEARTBEAT.autopilot -> "ardupilot" | "px4" | "other"."""
    if autopilot == AUTOPILOT_ARDUPILOT:
        return "ardupilot"
    if autopilot == AUTOPILOT_PX4:
        return "px4"
    return "other"


def _req(msg_type: str, name: str, v: float) -> float:
    v = float(v)
    if not math.isfinite(v):
        raise NonFiniteField(msg_type, name, v)
    return v


def _vec_req(msg_type: str, msg, names: tuple[str, str, str], scale: float) -> np.ndarray:
    return np.array([_req(msg_type, n, getattr(msg, n)) * scale for n in names])


class OptionalFieldCounter:
    """Collects how many optional fields were non-finite (the link adds it to its stats)."""
    __slots__ = ("count",)

    def __init__(self):
        self.count = 0

    def scalar(self, v: float, scale: float = 1.0, offset: float = 0.0) -> float | None:
        v = float(v)
        if not math.isfinite(v):
            self.count += 1
            return None
        return v * scale + offset

    def vec(self, msg, names: tuple[str, str, str], scale: float) -> np.ndarray | None:
        vals = [float(getattr(msg, n)) for n in names]
        if not all(math.isfinite(v) for v in vals):
            self.count += 1
            return None
        return np.array(vals) * scale


_ACC = ("xacc", "yacc", "zacc")
_GYRO = ("xgyro", "ygyro", "zgyro")
_MAG = ("xmag", "ymag", "zmag")


def decode_raw_imu(msg, time_fc_s: float, time_rx_s: float) -> ImuSample:
    """RAW_IMU (ArduPilot): mG, mrad/s, mgauss -> m/s^2, rad/s, gauss."""
    return _decode_milli_imu("RAW_IMU", msg, time_fc_s, time_rx_s, int(getattr(msg, "id", 0) or 0))


def decode_scaled_imu(msg, time_fc_s: float, time_rx_s: float) -> ImuSample:
    """SCALED_IMU: mG, mrad/s, mgauss -> m/s^2, rad/s, gauss (imu 0)."""
    return _decode_milli_imu("SCALED_IMU", msg, time_fc_s, time_rx_s, 0)


def _decode_milli_imu(msg_type: str, msg, time_fc_s: float, time_rx_s: float, imu_id: int) -> ImuSample:
    # integer fields: always finite
    accel = np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float) * MG_TO_M_S2
    gyro = np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float) * MRAD_TO_RAD
    mag_raw = (msg.xmag, msg.ymag, msg.zmag)
    mag = None if mag_raw == (0, 0, 0) else np.array(mag_raw, dtype=float) * MGAUSS_TO_GAUSS
    return ImuSample(time_fc_s, time_rx_s, gyro, accel, mag, msg_type, imu_id)


def decode_highres_imu(msg, time_fc_s: float, time_rx_s: float,
                       opt: OptionalFieldCounter | None = None) -> tuple[ImuSample, PressureSample | None]:
    """HIGHRES_IMU (PX4): m/s^2, rad/s, gauss, hPa, degC -> ImuSample (+ PressureSample if the
    message carries a fresh absolute pressure)."""
    opt = opt if opt is not None else OptionalFieldCounter()
    upd = int(msg.fields_updated) or 0xFFFF
    if (upd & (HR_ACC | HR_GYRO)) != (HR_ACC | HR_GYRO):
        raise NonFiniteField("HIGHRES_IMU", "fields_updated", float("nan"))
    accel = _vec_req("HIGHRES_IMU", msg, _ACC, 1.0)
    gyro = _vec_req("HIGHRES_IMU", msg, _GYRO, 1.0)
    mag = opt.vec(msg, _MAG, 1.0) if (upd & HR_MAG) == HR_MAG else None
    imu = ImuSample(time_fc_s, time_rx_s, gyro, accel, mag, "HIGHRES_IMU", int(getattr(msg, "id", 0) or 0))
    press = None
    if upd & HR_ABS_PRESSURE:
        p_abs = opt.scalar(msg.abs_pressure, HPA_TO_PA)
        if p_abs is not None:
            p_diff = opt.scalar(msg.diff_pressure, HPA_TO_PA) if upd & HR_DIFF_PRESSURE else None
            temp = opt.scalar(msg.temperature, 1.0, ZERO_CELSIUS_K) if upd & HR_TEMPERATURE else None
            press = PressureSample(time_fc_s, time_rx_s, p_abs, p_diff, temp, "HIGHRES_IMU")
    return imu, press


def decode_scaled_pressure(msg, time_fc_s: float, time_rx_s: float,
                           opt: OptionalFieldCounter | None = None) -> PressureSample:
    """SCALED_PRESSURE: press_abs/press_diff hPa, temperature cdegC -> Pa, Pa, K."""
    opt = opt if opt is not None else OptionalFieldCounter()
    p_abs = _req("SCALED_PRESSURE", "press_abs", msg.press_abs) * HPA_TO_PA
    p_diff = opt.scalar(msg.press_diff, HPA_TO_PA)
    temp_k = float(msg.temperature) * CDEGC_TO_DEGC + ZERO_CELSIUS_K  # int16: always finite
    return PressureSample(time_fc_s, time_rx_s, p_abs, p_diff, temp_k, "SCALED_PRESSURE")


def decode_attitude(msg, time_fc_s: float, time_rx_s: float) -> FcAttitude:
    """ATTITUDE: roll/pitch/yaw rad, body rates rad/s (all required)."""
    roll = _req("ATTITUDE", "roll", msg.roll)
    pitch = _req("ATTITUDE", "pitch", msg.pitch)
    yaw = _req("ATTITUDE", "yaw", msg.yaw)
    rates = _vec_req("ATTITUDE", msg, ("rollspeed", "pitchspeed", "yawspeed"), 1.0)
    return FcAttitude(time_fc_s, time_rx_s, roll, pitch, yaw, rates)


def decode_heartbeat(msg, time_rx_s: float) -> FcHeartbeat:
    return FcHeartbeat(time_rx_s, msg.get_srcSystem(), msg.get_srcComponent(), autopilot_name(msg.autopilot),
                       int(msg.type), int(msg.base_mode), int(msg.custom_mode), int(msg.system_status),
                       bool(msg.base_mode & MODE_FLAG_SAFETY_ARMED))


def decode_ekf_status_report(msg, time_rx_s: float, opt: OptionalFieldCounter | None = None) -> FcEkfStatus:
    """EKF_STATUS_REPORT (ArduPilot): flags + normalised innovation variances."""
    opt = opt if opt is not None else OptionalFieldCounter()
    flags = int(msg.flags)
    att_ok = bool(flags & EST_ATTITUDE) and not (flags & EKF_UNINITIALIZED)
    return FcEkfStatus(time_rx_s, att_ok, bool(flags & EST_POS_HORIZ_ABS), flags, "EKF_STATUS_REPORT",
                       None, opt.scalar(msg.velocity_variance), opt.scalar(msg.pos_horiz_variance),
                       opt.scalar(msg.pos_vert_variance), opt.scalar(msg.compass_variance))


def decode_estimator_status(msg, time_fc_s: float, time_rx_s: float,
                            opt: OptionalFieldCounter | None = None) -> FcEkfStatus:
    """ESTIMATOR_STATUS (PX4): flags + innovation test ratios."""
    opt = opt if opt is not None else OptionalFieldCounter()
    flags = int(msg.flags)
    return FcEkfStatus(time_rx_s, bool(flags & EST_ATTITUDE), bool(flags & EST_POS_HORIZ_ABS), flags,
                       "ESTIMATOR_STATUS", time_fc_s, opt.scalar(msg.vel_ratio),
                       opt.scalar(msg.pos_horiz_ratio), opt.scalar(msg.pos_vert_ratio),
                       opt.scalar(msg.mag_ratio))


def _health(present: int, enabled: int, health: int, bit: int) -> bool | None:
    if not (present & bit and enabled & bit):
        return None
    return bool(health & bit)


def decode_sys_status(msg, time_rx_s: float) -> FcSysStatus:
    p = int(msg.onboard_control_sensors_present)
    e = int(msg.onboard_control_sensors_enabled)
    h = int(msg.onboard_control_sensors_health)
    volt = None if msg.voltage_battery in (0xFFFF, -1) else msg.voltage_battery * 1e-3  # mV -> V
    return FcSysStatus(time_rx_s, p, e, h,
                       _health(p, e, h, SENSOR_GYRO), _health(p, e, h, SENSOR_ACCEL),
                       _health(p, e, h, SENSOR_MAG), _health(p, e, h, SENSOR_ABS_PRESSURE),
                       _health(p, e, h, SENSOR_DIFF_PRESSURE), _health(p, e, h, SENSOR_GPS),
                       _health(p, e, h, SENSOR_AHRS),
                       msg.load * 1e-3,  # d% -> fraction
                       volt, msg.drop_rate_comm * 1e-4)  # c% -> fraction


def decode_command_ack(msg, time_rx_s: float) -> CommandAck:
    return CommandAck(time_rx_s, int(msg.command), int(msg.result), int(getattr(msg, "progress", 0) or 0),
                      int(getattr(msg, "result_param2", 0) or 0), int(getattr(msg, "target_system", 0) or 0),
                      int(getattr(msg, "target_component", 0) or 0))


# EXTENDED_SYS_STATE.landed_state (MAV_LANDED_STATE): the FC's land detector
LANDED_STATE_LANDED = {0: None, 1: True, 2: False, 3: False, 4: False}
"""UNDEFINED -> None (not said), ON_GROUND -> landed, IN_AIR / TAKEOFF / LANDING -> in the air
(FcFlightState.landed: taking off and landing count as in the air)."""


def decode_extended_sys_state(msg, time_rx_s: float) -> FcFlightState:
    """EXTENDED_SYS_STATE (no timestamp; armed is the HEARTBEAT's, so None here). A landed_state
    outside the enum says nothing (None), it does not fail the message."""
    return FcFlightState(None, time_rx_s, None, LANDED_STATE_LANDED.get(int(msg.landed_state)),
                         "EXTENDED_SYS_STATE")


# --- STATUSTEXT and PARAM_VALUE ----------------------------------------------------------------

STATUSTEXT_CHUNK_CHARS = 50
"""STATUSTEXT.text is 50 characters; a longer text comes in chunks sharing a nonzero ``id``, numbered
by ``chunk_seq``; the last chunk is shorter than 50 (ArduPilot splits "Requested rate for message ID
27 too fast. Increase SCHED_LOOP_RATE" in two)."""
STATUSTEXT_MAX_CHUNKS = 8


@dataclass(frozen=True, slots=True)
class FcStatusText:
    """A whole STATUSTEXT from the FC (chunks joined). severity: MAV_SEVERITY (0 emergency .. 7 debug)."""
    time_rx_s: float
    severity: int
    text: str


@dataclass(frozen=True, slots=True)
class FcParam:
    """One PARAM_VALUE from the FC: the name and its value as a number (PX4's bytewise integers
    already reinterpreted)."""
    time_rx_s: float
    name: str
    value: float


class StatusTextAssembler:
    """Joins STATUSTEXT chunks. ``feed`` returns the whole text once its last chunk arrived (a
    message with id 0 is whole); a chunk of another id, or out of order, drops the one in progress."""

    def __init__(self):
        self._id = 0
        self._parts: list[str] = []

    def feed(self, text: str, msg_id: int, chunk_seq: int) -> str | None:
        if msg_id == 0:
            return text
        if msg_id != self._id or chunk_seq != len(self._parts):
            self._id, self._parts = msg_id, []
            if chunk_seq != 0:
                return None
        self._parts.append(text)
        if len(text) < STATUSTEXT_CHUNK_CHARS or len(self._parts) >= STATUSTEXT_MAX_CHUNKS:
            whole, self._id, self._parts = "".join(self._parts), 0, []
            return whole
        return None


def _text(v) -> str:
    if isinstance(v, (bytes, bytearray)):
        v = bytes(v).decode("utf-8", "replace")
    return str(v).split("\x00", 1)[0]


def decode_statustext(msg, asm: StatusTextAssembler, time_rx_s: float) -> FcStatusText | None:
    """STATUSTEXT -> FcStatusText once whole (None while chunks are missing)."""
    text = asm.feed(_text(msg.text), int(getattr(msg, "id", 0) or 0), int(getattr(msg, "chunk_seq", 0) or 0))
    return None if text is None else FcStatusText(time_rx_s, int(msg.severity), text)


MAV_PARAM_TYPE_INT_MAX = 8
"""MAV_PARAM_TYPE 1..8 are integers (UINT8 .. INT64), 9 REAL32."""


def decode_param_value(msg, time_rx_s: float, bytewise: bool) -> FcParam:
    """PARAM_VALUE -> FcParam. ``bytewise`` (PX4): an integer parameter's bits are carried in the
    float field (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE) and are reinterpreted here;
    ArduPilot casts integers to float. A non-finite REAL32 raises NonFiniteField."""
    import struct
    value = float(msg.param_value)
    ptype = int(msg.param_type)
    if bytewise and 1 <= ptype <= MAV_PARAM_TYPE_INT_MAX:
        raw = struct.pack("<f", value)
        value = float(struct.unpack("<i", raw)[0] if ptype in (6, 8) else struct.unpack("<I", raw)[0])
        if ptype in (1, 2):  # UINT8 / INT8 in the low byte
            value = float(raw[0] if ptype == 1 else struct.unpack("<b", raw[:1])[0])
        elif ptype in (3, 4):  # UINT16 / INT16 in the low two bytes
            value = float(struct.unpack("<H" if ptype == 3 else "<h", raw[:2])[0])
    return FcParam(time_rx_s, _text(msg.param_id), _req("PARAM_VALUE", "param_value", value))
