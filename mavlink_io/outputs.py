"""MAVLink output encoders: NavSolution -> pymavlink messages, and when each one is due.

Pure functions: no sockets, no clocks. The daemon calls ``OutputScheduler.messages(sol, now_s)``
for every NavSolution and hands the returned messages to ``MavlinkLink.send``; the link packs
them with our identity (the vehicle's system id, component 191).

Messages (docs/OUTPUTS.md has the user's view, the FC parameters and the sources quoted here):

- ATTITUDE (#30): roll, pitch, yaw and body rates. ``yaw`` is NaN while no heading is valid
  (roll and pitch do not depend on a heading source, so they are still worth sending).
- ATTITUDE_QUATERNION (#31): only while the heading is valid: a quaternion cannot say
  "yaw unknown".
- ODOMETRY (#331): the heading feed the FC's EKF fuses (ArduPilot EK3_SRC1_YAW=6 ExternalNav,
  PX4 EKF2_EV_CTRL bit 3 yaw). Only while the heading is valid and its sigma is known. Its
  encoding depends on the consumer (``OdometryProfile``), because both autopilots reject the
  MAVLink spec's "unknown position = NaN" in ways that also throw away the yaw:

  * ArduPilot (GCS_MAVLINK::handle_odometry -> AP_VisualOdom -> NavEKF3_core::writeExtNavData)
    accepts only frame_id MAV_FRAME_LOCAL_FRD with child_frame_id MAV_FRAME_BODY_FRD, and
    writeExtNavData returns before it stores the yaw when the position or its error is NaN.
    The yaw error it uses is angErr = cbrt(c15^2 + c18^2 + c20^2) (variances, rad^2) when
    pose_covariance[0] is finite, else 0; AP_VisualOdom then constrains it to
    [VISO_YAW_M_NSE, 1.5] and the EKF to >= 5 deg.
  * PX4 (MavlinkReceiver::handle_message_odometry -> EKF2 ev_yaw_control) sets the pose frame
    only when x, y, z are finite; with NaN position the EKF's default frame is FRD and EV yaw
    starts as a *relative* heading (yaw_align cleared, refused while GNSS is used). An absolute
    heading needs frame_id MAV_FRAME_LOCAL_NED *and* a finite position. The yaw variance is read
    from pose_covariance[20] whenever q is finite (estimator_type not NAIVE), floored at
    EKF2_EVA_NOISE^2.

  So the ardupilot and px4 profiles send a finite placeholder position (0, 0, 0) with a huge
  finite position variance, and the user must leave position/velocity sources off ExtNav/EV
  (docs/OUTPUTS.md). The ``mavlink`` profile follows the message spec literally (NaN position)
  for generic consumers. Velocity and angular rates are NaN in every profile (unknown; ArduPilot
  forks route finite rates to a body-velocity path), velocity_covariance[0] = NaN (unknown).
- NAMED_VALUE_FLOAT: ``az_deg`` (flight azimuth, deg), ``hdg_deg`` (heading, deg),
  ``hdg_sd_deg`` (heading 1-sigma, deg), ``phase`` (PHASE_CODES) for ground stations.

Time stamps are the FC clock of the solution (``time_fc_s``: its IMU sample's, plus the age it was
brought forward by, mavlink_io/output_gate.py), so the FC
can match our output to its own data without TIMESYNC (PX4's sync_stamp passes an unsynced
time through; ArduPilot's offboard jitter correction estimates any offset).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as mavlink2

if TYPE_CHECKING:  # encoders only read its attributes
    from mavlink_io.navsolution import NavSolution

NAN = float("nan")

PHASE_CODES: dict[str, int] = {"boot": 0, "pre-launch": 1, "launch": 2, "in-flight": 3}
"""NAMED_VALUE_FLOAT ``phase`` value for each NavSolution.phase (unknown phase: -1)."""

NAMED_VALUE_NAME_MAX_CHARS = 10
NV_AZIMUTH = "az_deg"
NV_HEADING = "hdg_deg"
NV_HEADING_SIGMA = "hdg_sd_deg"
NV_PHASE = "phase"

POSE_COV_SIZE = 21
"""Upper-right triangle of the 6x6 pose covariance (x, y, z, roll, pitch, yaw), row-major."""
POSE_COV_INDEX_X = 0
POSE_COV_INDEX_Y = 6
POSE_COV_INDEX_Z = 11
POSE_COV_INDEX_ROLL = 15
POSE_COV_INDEX_PITCH = 18
POSE_COV_INDEX_YAW = 20

POSITION_VARIANCE_UNCONSTRAINED_M2 = 1.0e6
"""Position variance sent with the placeholder position: (1 km)^2, i.e. "no information".
Finite on purpose (ArduPilot drops the whole sample, yaw included, on a NaN position error)."""

QUALITY_ZERO_SIGMA_DEG = 30.0
"""ODOMETRY.quality = 100 * (1 - sigma/30 deg), clipped to [1, 100] (0 would mean 'unknown')."""

RESET_JUMP_SIGMAS = 3.0
RESET_JUMP_MIN_RAD = math.radians(2.0)
"""ODOMETRY.reset_counter steps on a heading step above max(3 sigma, 2 deg) beyond the body rates'
prediction between consecutive solutions (OutputScheduler)."""

MIN_ODOMETRY_RATE_HZ = 5.0
"""The EKFs time out an ExtNav/EV yaw source after a few hundred ms; 5 Hz is the floor."""

DEFAULT_RATES_HZ: dict[str, float] = {
    "ATTITUDE": 20.0,
    "ATTITUDE_QUATERNION": 20.0,
    "ODOMETRY": 10.0,
    "NAMED_VALUE_FLOAT": 2.0,
}
"""Output rates, Hz (config [outputs] rates). 0 disables a message (not allowed for ODOMETRY)."""


@dataclass(frozen=True, slots=True)
class OdometryProfile:
    """How ODOMETRY is encoded for one consumer (see the module docstring for the why)."""

    name: str
    frame_id: int
    """Pose frame: MAV_FRAME_LOCAL_FRD (ArduPilot) or MAV_FRAME_LOCAL_NED (PX4, spec)."""
    child_frame_id: int
    """Twist frame: MAV_FRAME_BODY_FRD (required by ArduPilot)."""
    position_m: float
    """Value sent in x, y, z: 0.0 (finite placeholder) or NaN (spec: unknown)."""
    position_variance_m2: float
    """Diagonal position variances (covariance indices 0, 6, 11)."""


ODOMETRY_PROFILES: dict[str, OdometryProfile] = {
    "ardupilot": OdometryProfile("ardupilot", mavlink2.MAV_FRAME_LOCAL_FRD,
                                 mavlink2.MAV_FRAME_BODY_FRD, 0.0,
                                 POSITION_VARIANCE_UNCONSTRAINED_M2),
    "px4": OdometryProfile("px4", mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD,
                           0.0, POSITION_VARIANCE_UNCONSTRAINED_M2),
    "mavlink": OdometryProfile("mavlink", mavlink2.MAV_FRAME_LOCAL_NED,
                               mavlink2.MAV_FRAME_BODY_FRD, NAN,
                               POSITION_VARIANCE_UNCONSTRAINED_M2),
}


def odometry_profile_for_autopilot(autopilot: int | str | None) -> OdometryProfile:
    """Profile for the FC's autopilot: HEARTBEAT.autopilot (MAV_AUTOPILOT_*) or FcHeartbeat's
    "ardupilot" / "px4" / "other"; anything else or None -> ``mavlink``."""
    if autopilot in (mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, "ardupilot"):
        return ODOMETRY_PROFILES["ardupilot"]
    if autopilot in (mavlink2.MAV_AUTOPILOT_PX4, "px4"):
        return ODOMETRY_PROFILES["px4"]
    return ODOMETRY_PROFILES["mavlink"]


def _time_boot_ms(time_fc_s: float) -> int:
    if not math.isfinite(time_fc_s) or time_fc_s < 0.0:
        raise ValueError(f"time_fc_s must be finite and >= 0, got {time_fc_s}")
    return int(round(time_fc_s * 1e3)) & 0xFFFFFFFF  # uint32 ms wraps after 49.7 days


def _time_usec(time_fc_s: float) -> int:
    if not math.isfinite(time_fc_s) or time_fc_s < 0.0:
        raise ValueError(f"time_fc_s must be finite and >= 0, got {time_fc_s}")
    return int(round(time_fc_s * 1e6))


def _wrap_pi(angle_rad: float) -> float:
    """Wrap to [-pi, pi) (ATTITUDE.yaw's range)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def _rates(sol: NavSolution) -> tuple[float, float, float]:
    if sol.rates_body_rad_s is None:
        return (NAN, NAN, NAN)
    p, q, r = (float(v) for v in sol.rates_body_rad_s)
    return (p, q, r)


def _finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


def _unit_quaternion(sol: NavSolution) -> tuple[float, float, float, float] | None:
    if sol.q_nav_from_body is None:
        return None
    w, x, y, z = (float(v) for v in sol.q_nav_from_body)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n < 0.5:
        return None
    if w < 0.0:  # one representative of +-q, scalar part >= 0
        n = -n
    return (w / n, x / n, y / n, z / n)


def heading_usable(sol: NavSolution) -> bool:
    """True when the heading may go to the FC: valid, finite, with a finite positive sigma."""
    return bool(sol.heading_valid and _finite(sol.heading_rad) and _finite(sol.heading_sigma_rad)
                and sol.heading_sigma_rad > 0.0 and _unit_quaternion(sol) is not None)


def encode_attitude(sol: NavSolution) -> mavlink2.MAVLink_attitude_message | None:
    """ATTITUDE (#30) from roll, pitch, heading (yaw = NaN when no valid heading); None
    without roll/pitch. time_boot_ms = FC time of the sample, ms."""
    if not (_finite(sol.roll_rad) and _finite(sol.pitch_rad)):
        return None
    yaw = _wrap_pi(sol.heading_rad) if (sol.heading_valid and _finite(sol.heading_rad)) else NAN
    p, q, r = _rates(sol)
    return mavlink2.MAVLink_attitude_message(_time_boot_ms(sol.time_fc_s), float(sol.roll_rad),
                                             float(sol.pitch_rad), yaw, p, q, r)


def encode_attitude_quaternion(
        sol: NavSolution) -> mavlink2.MAVLink_attitude_quaternion_message | None:
    """ATTITUDE_QUATERNION (#31), q = q_nav_from_body [w, x, y, z]; only with a valid heading."""
    quat = _unit_quaternion(sol)
    if quat is None or not sol.heading_valid:
        return None
    p, q, r = _rates(sol)
    return mavlink2.MAVLink_attitude_quaternion_message(
        _time_boot_ms(sol.time_fc_s), *quat, p, q, r, [0.0, 0.0, 0.0, 0.0])


def odometry_quality(heading_sigma_rad: float) -> int:
    """ODOMETRY.quality in [1, 100] from the heading 1-sigma (QUALITY_ZERO_SIGMA_DEG)."""
    sigma_deg = math.degrees(heading_sigma_rad)
    return int(min(100, max(1, round(100.0 * (1.0 - sigma_deg / QUALITY_ZERO_SIGMA_DEG)))))


def pose_covariance(sol: NavSolution, profile: OdometryProfile) -> list[float]:
    """The 21-element upper triangle: position variances = profile's (unconstrained), roll and
    pitch variances from their sigmas (the yaw variance where unknown: conservative for
    ArduPilot's combined angErr; neither EKF fuses roll/pitch from ODOMETRY), yaw variance =
    heading_sigma^2, all cross terms 0. Element 0 is finite: a NaN there would mark the whole
    matrix, yaw variance included, as unknown."""
    yaw_var = float(sol.heading_sigma_rad) ** 2
    roll_var = float(sol.roll_sigma_rad) ** 2 if _finite(sol.roll_sigma_rad) else yaw_var
    pitch_var = float(sol.pitch_sigma_rad) ** 2 if _finite(sol.pitch_sigma_rad) else yaw_var
    cov = [0.0] * POSE_COV_SIZE
    cov[POSE_COV_INDEX_X] = cov[POSE_COV_INDEX_Y] = cov[POSE_COV_INDEX_Z] = \
        profile.position_variance_m2
    cov[POSE_COV_INDEX_ROLL] = roll_var
    cov[POSE_COV_INDEX_PITCH] = pitch_var
    cov[POSE_COV_INDEX_YAW] = yaw_var
    return cov


def encode_odometry(sol: NavSolution, profile: OdometryProfile,
                    reset_counter: int = 0) -> mavlink2.MAVLink_odometry_message | None:
    """ODOMETRY (#331), the FC's heading feed; None unless ``heading_usable(sol)``.

    q = q_nav_from_body (body FRD -> NED), x/y/z = profile.position_m, velocities and rates NaN,
    pose_covariance from ``pose_covariance``, velocity_covariance[0] = NaN (unknown),
    estimator_type VISION (PX4 routes it to vehicle_visual_odometry; NAIVE would ignore the
    covariance), quality from ``odometry_quality``, time_usec = FC time of the sample."""
    if not heading_usable(sol):
        return None
    if not 0 <= reset_counter <= 255:
        raise ValueError(f"reset_counter must be in [0, 255], got {reset_counter}")
    quat = _unit_quaternion(sol)
    pos = profile.position_m
    vel_cov = [NAN] + [0.0] * (POSE_COV_SIZE - 1)
    return mavlink2.MAVLink_odometry_message(
        _time_usec(sol.time_fc_s), profile.frame_id, profile.child_frame_id, pos, pos, pos,
        list(quat), NAN, NAN, NAN, NAN, NAN, NAN, pose_covariance(sol, profile), vel_cov,
        reset_counter, mavlink2.MAV_ESTIMATOR_TYPE_VISION,
        odometry_quality(float(sol.heading_sigma_rad)))


def _named_value(time_boot_ms: int, name: str, value: float
                 ) -> mavlink2.MAVLink_named_value_float_message:
    if len(name) > NAMED_VALUE_NAME_MAX_CHARS:
        raise ValueError(f"NAMED_VALUE_FLOAT name {name!r} longer than 10 characters")
    return mavlink2.MAVLink_named_value_float_message(time_boot_ms, name.encode("ascii"), value)


def encode_named_values(sol: NavSolution) -> list[mavlink2.MAVLink_named_value_float_message]:
    """NAMED_VALUE_FLOAT for ground stations: phase always; az_deg when the azimuth is known;
    hdg_deg and hdg_sd_deg while the heading is valid. Degrees, heading/azimuth in [0, 360)."""
    t_ms = _time_boot_ms(sol.time_fc_s)
    out = [_named_value(t_ms, NV_PHASE, float(PHASE_CODES.get(sol.phase, -1)))]
    if _finite(sol.azimuth_rad):
        out.append(_named_value(t_ms, NV_AZIMUTH, math.degrees(sol.azimuth_rad) % 360.0))
    if sol.heading_valid and _finite(sol.heading_rad):
        out.append(_named_value(t_ms, NV_HEADING, math.degrees(sol.heading_rad) % 360.0))
        if _finite(sol.heading_sigma_rad):
            out.append(_named_value(t_ms, NV_HEADING_SIGMA, math.degrees(sol.heading_sigma_rad)))
    return out


class OutputScheduler:
    """Decides per message whether it is due at its configured rate, and builds what is due.

    Rates in Hz (``DEFAULT_RATES_HZ`` keys); 0 disables a message, ODOMETRY must be >= 5 Hz.
    A message is due when ``now_s`` reaches its next slot; slots advance by one period so the
    mean rate is exact under IMU-sample jitter, and re-synchronise after a gap. ODOMETRY is
    only produced while the heading is usable and ``odometry_allowed`` (the daemon clears it while
    the FC's parameters say the placeholder position could be fused, mavlink_io.fc_yaw_feed);
    ``reset_counter`` counts real heading discontinuities: the heading usable again after a gap, or a
    step between consecutive solutions larger than RESET_JUMP_SIGMAS sigma (and RESET_JUMP_MIN_RAD)
    beyond what the body rates explain. A change of the source *name* is not one: the arbitration
    blends source changes (service/heading_arbitration), so the published heading is continuous.
    """

    def __init__(self, rates_hz: Mapping[str, float] | None = None,
                 profile: OdometryProfile | None = None):
        rates = dict(DEFAULT_RATES_HZ)
        for name, rate in (rates_hz or {}).items():
            if name not in DEFAULT_RATES_HZ:
                raise ValueError(f"outputs rate: unknown message {name!r}, "
                                 f"expected one of {sorted(DEFAULT_RATES_HZ)}")
            if not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate < 0:
                raise ValueError(f"outputs rate for {name} must be a finite number >= 0 Hz, "
                                 f"got {rate!r}")
            rates[name] = float(rate)
        if rates["ODOMETRY"] < MIN_ODOMETRY_RATE_HZ:
            raise ValueError(f"outputs rate for ODOMETRY must be >= {MIN_ODOMETRY_RATE_HZ} Hz, "
                             f"got {rates['ODOMETRY']}")
        self.rates_hz: dict[str, float] = rates
        self.profile: OdometryProfile = profile or ODOMETRY_PROFILES["mavlink"]
        self._next_due_s: dict[str, float | None] = {name: None for name in rates}
        self.reset_counter = 0
        self.odometry_allowed = True
        self.odometry_late = 0
        """ODOMETRY not sent because the solution lagged the FC's clock (``messages(..., late=True)``)."""
        self._last_heading: tuple[float, float] | None = None
        """(FC time s, heading rad) of the last usable heading."""
        self._ever_usable = False
        self._heading_was_usable = False

    def set_profile(self, profile: OdometryProfile) -> None:
        """Switch the ODOMETRY encoding (e.g. once the FC's HEARTBEAT names its autopilot)."""
        self.profile = profile

    def due(self, name: str, now_s: float) -> bool:
        """True (and the slot consumed) when ``name`` is due at local time ``now_s`` (s)."""
        rate = self.rates_hz[name]
        if rate <= 0.0:
            return False
        period = 1.0 / rate
        next_due = self._next_due_s[name]
        if next_due is None or now_s >= next_due:
            if next_due is None or now_s - next_due > period:
                next_due = now_s  # first call, or a gap: re-synchronise
            self._next_due_s[name] = next_due + period
            return True
        return False

    def next_due_s(self) -> float:
        """Local time at which the next message is due (-inf before the first call)."""
        dues = [d if d is not None else -math.inf for n, d in self._next_due_s.items() if self.rates_hz[n] > 0]
        return min(dues) if dues else math.inf

    def next_slot_after(self, now_s: float) -> float | None:
        """The earliest slot of an enabled message later than ``now_s`` (None: none). A slot
        already past belongs to a message the last solution did not produce (ATTITUDE_QUATERNION
        without a valid heading, ODOMETRY not allowed): it passes when a solution that has it comes,
        and is no reason to wake the daemon's loop (Daemon.loop_wait_s)."""
        later = [d for n, d in self._next_due_s.items() if self.rates_hz[n] > 0 and d is not None and d > now_s]
        return min(later) if later else None

    def _heading_jumped(self, sol: NavSolution) -> bool:
        if self._last_heading is None:
            return False
        t0, h0 = self._last_heading
        dt = sol.time_fc_s - t0
        predicted = 0.0
        if sol.rates_body_rad_s is not None and _finite(sol.roll_rad) and _finite(sol.pitch_rad) \
                and abs(math.cos(sol.pitch_rad)) > 1e-3 and 0.0 < dt < 1.0:
            _p, q, r = _rates(sol)  # psi_dot = (q sin(phi) + r cos(phi)) / cos(theta)
            rate = (q * math.sin(sol.roll_rad) + r * math.cos(sol.roll_rad)) / math.cos(sol.pitch_rad)
            predicted = rate * dt if math.isfinite(rate) else 0.0
        step = abs(_wrap_pi(float(sol.heading_rad) - h0 - predicted))
        return step > max(RESET_JUMP_MIN_RAD, RESET_JUMP_SIGMAS * float(sol.heading_sigma_rad))

    def _track_resets(self, sol: NavSolution) -> None:
        usable = heading_usable(sol)
        if usable and self._ever_usable and (not self._heading_was_usable or self._heading_jumped(sol)):
            self.reset_counter = (self.reset_counter + 1) % 256  # the very first start is not a reset
        if usable:
            self._ever_usable = True
            self._last_heading = (sol.time_fc_s, float(sol.heading_rad))
        self._heading_was_usable = usable

    def messages(self, sol: NavSolution, now_s: float, late: bool = False) -> list:
        """All messages due for this solution at local monotonic time ``now_s`` (s). ``late``: the
        solution lags the FC's clock beyond what the FC can date (output_gate.ODOMETRY_MAX_LAG_S): its
        ODOMETRY slot passes without one (counted in ``odometry_late``), the rest goes as usual."""
        self._track_resets(sol)
        out: list = []
        if self.due("ATTITUDE", now_s):
            msg = encode_attitude(sol)
            if msg is not None:
                out.append(msg)
        if sol.heading_valid and self.due("ATTITUDE_QUATERNION", now_s):
            msg = encode_attitude_quaternion(sol)
            if msg is not None:
                out.append(msg)
        if self.odometry_allowed and heading_usable(sol) and self.due("ODOMETRY", now_s):
            if late:
                self.odometry_late += 1
            else:
                out.append(encode_odometry(sol, self.profile, self.reset_counter))
        if self.due("NAMED_VALUE_FLOAT", now_s):
            out.extend(encode_named_values(sol))
        return out
