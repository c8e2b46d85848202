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

from mavlink_io.output_gate import ODOMETRY_MAX_LAG_S

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


SLOT_EPSILON = 1e-6
"""Fraction of a slot: a sample stamped on a slot's boundary (to floating-point rounding of its FC time)
belongs to that slot."""

CATCH_UP_MAX_LAG_S = ODOMETRY_MAX_LAG_S
"""Catch-up cap (s): a slot whose solution lags the FC's clock by more than this (its IMU sample against
the FC's clock, output_gate.FcLagMeter) is *late*. The FC's EKFs take a delayed measurement by its time
stamp only within their fusion horizon: ArduPilot's EKF3 (NavEKF3_core::writeExtNavData) moves a sample
older than its delayed IMU time up to that time (fused misdated), and its observation buffer recalls only
samples less than 100 ms before it; PX4's EKF2 (EstimatorInterface::setExtVisionData,
RingBuffer::pop_first_older_than) fuses a sample only within 100 ms before its delayed horizon and drops
older ones. The horizon is the EKF's largest sensor delay, about 0.2 s (output_gate.ODOMETRY_MAX_LAG_S,
measured against ArduPlane). So a late ODOMETRY is never sent (``odometry_late``). The other messages
(ATTITUDE, ATTITUDE_QUATERNION, NAMED_VALUE_FLOAT) are fused by no EKF: late, they are sent at most at
their rate of the local clock, each slot still with its own solution (``slots_behind``), and the rest
of a catch-up burst is skipped (``slots_late``), so a daemon that works off a stall does not flood a
telemetry link, and one that stays behind (a slow computer) still shows its attitude, stamped."""


class OutputScheduler:
    """Decides per message whether it is due at its configured rate, and builds what is due.

    Rates in Hz (``DEFAULT_RATES_HZ`` keys); 0 disables a message, ODOMETRY must be >= 5 Hz.

    Slots are on the FC's clock: slot k of a message at rate f covers FC time [k/f, (k+1)/f). Each
    solution (its IMU sample's FC time) is offered in sample order (``messages``); the first solution in
    a slot fills it, with its own values and time stamp. So a burst of input worked off at once (the
    loop behind after a stall) sends one message per slot, each the solution of that slot's sample, the
    same set a replay of the same input sends. Slots older than CATCH_UP_MAX_LAG_S (``late``) are not
    sent if ODOMETRY, and paced on the local clock otherwise (see there): counted in ``slots_late``
    when skipped. Slots no solution fell in (the FC's samples stopped, or came
    sparser than the slots) are counted in ``slots_gap`` when the next solution comes.

    When the FC's samples are sparser than half a slot (e.g. ArduPlane's stock 25 Hz RAW_IMU against
    50 Hz ATTITUDE), a slot between two samples has none of its own: ``fill`` sends it on the local
    clock, at the time the slot's FC time is reached, with the newest solution (repeated with its own
    stamp if it was already sent), counted in ``slots_filled``. The daemon does so only while that
    solution is fresher than max_extrapolation_s, so the configured rates hold whatever the IMU rate.

    ODOMETRY is only produced while the heading is usable and ``odometry_allowed`` (the daemon clears it
    while the FC's parameters say the placeholder position could be fused, mavlink_io.fc_yaw_feed);
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
        self._enabled = tuple(n for n, r in rates.items() if r > 0.0)
        self._dense_s = min((0.5 / rates[n] for n in self._enabled), default=math.inf)
        """A sample interval up to this leaves no enabled message fillable (``_fillable``): ``next_fill_s``
        says None at once (the daemon asks twice per wake-up, the samples are dense in flight)."""
        self.profile: OdometryProfile = profile or ODOMETRY_PROFILES["mavlink"]
        self._last_slot: dict[str, int | None] = {name: None for name in rates}
        """Per message: the FC-time slot last taken (sent, or passed by a solution that had no such message)."""
        self._next_slot_fc_s = -math.inf
        """FC time of the earliest next slot of an enabled message (-inf before the first solution)."""
        self.slots_late: dict[str, int] = {name: 0 for name in rates}
        """Slots whose message was not sent: its solution lagged the FC's clock by more than
        CATCH_UP_MAX_LAG_S (``messages(..., late=True)``): every late ODOMETRY, and the other messages
        beyond their rate on the local clock."""
        self.slots_behind: dict[str, int] = {name: 0 for name in rates}
        """Slots sent although late (not ODOMETRY; at most at the message's rate of the local clock)."""
        self._late_next_s: dict[str, float | None] = {name: None for name in rates}
        """Per message: local time from which a late message may go again (its rate on the local clock)."""
        self.slots_gap: dict[str, int] = {name: 0 for name in rates}
        """Slots that passed with no solution in them (no IMU sample processed in that FC time)."""
        self.slots_filled: dict[str, int] = {name: 0 for name in rates}
        """Slots sent on the local clock with the newest solution (``fill``: samples sparser than slots)."""
        self._offered: tuple[float, float] | None = None
        """(FC time s, local time s) of the newest solution offered."""
        self.sample_interval_s: float | None = None
        """FC time between the last two solutions offered (the FC's sample interval)."""
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

    def restart_fc_clock(self) -> None:
        """The FC rebooted (its clock restarts): its slots start again from its next sample."""
        self._last_slot = {name: None for name in self.rates_hz}
        self._next_slot_fc_s = -math.inf
        self._offered = None
        self.sample_interval_s = None
        self._last_heading = None
        self._late_next_s = {name: None for name in self.rates_hz}

    def slot_index(self, name: str, time_fc_s: float) -> int:
        """The slot of ``name`` that FC time ``time_fc_s`` (s) falls in (its rate must be > 0)."""
        if not math.isfinite(time_fc_s):
            raise ValueError(f"time_fc_s must be finite, got {time_fc_s}")
        return math.floor(time_fc_s * self.rates_hz[name] + SLOT_EPSILON)

    def _take(self, name: str, k: int) -> None:
        last = self._last_slot[name]
        if last is not None:
            self.slots_gap[name] += k - last - 1
        self._last_slot[name] = k
        # a little before the boundary (2 SLOT_EPSILON): only a pre-filter for ``due``, which decides
        self._next_slot_fc_s = min((self._last_slot[n] + 1 - 2.0 * SLOT_EPSILON) / self.rates_hz[n]
                                   if self._last_slot[n] is not None else -math.inf for n in self._enabled)

    def due(self, name: str, time_fc_s: float) -> bool:
        """True (and the slot taken) when a solution at FC time ``time_fc_s`` (s) is the first in a slot
        of ``name`` after the one taken last; the slots between are counted in ``slots_gap``."""
        if self.rates_hz[name] <= 0.0:
            return False
        k = self.slot_index(name, time_fc_s)
        last = self._last_slot[name]
        if last is not None and k <= last:
            return False
        self._take(name, k)
        return True

    def reaches_slot(self, time_fc_s: float) -> bool:
        """True when a solution at FC time ``time_fc_s`` would take a slot of some message (cheap: the
        daemon asks it for every IMU sample before it builds anything)."""
        return bool(self._enabled) and time_fc_s >= self._next_slot_fc_s

    def note(self, time_fc_s: float, now_s: float) -> None:
        """A solution at FC time ``time_fc_s`` was produced at local time ``now_s`` (every solution, in
        sample order, whether or not it takes a slot): the sample interval and what ``fill`` extends."""
        if self._offered is not None and time_fc_s > self._offered[0]:
            self.sample_interval_s = time_fc_s - self._offered[0]
        self._offered = (time_fc_s, now_s)

    def _fillable(self, name: str) -> bool:
        """Samples sparser than half a slot of ``name`` (or one sample so far): some of its slots fall
        between two samples."""
        return self._last_slot[name] is not None and (self.sample_interval_s is None
                                                      or self.sample_interval_s > 0.5 / self.rates_hz[name])

    def next_fill_s(self) -> float | None:
        """Local time at which ``fill`` has a slot to send (None: every slot gets a sample of its own, or no
        solution yet): the next slot's FC time carried to the local clock from the newest solution."""
        if self._offered is None or (self.sample_interval_s is not None and self.sample_interval_s <= self._dense_s):
            return None
        t_fc, t_local = self._offered
        times = [t_local + (self._last_slot[n] + 1) / self.rates_hz[n] - t_fc
                 for n in self._enabled if self._fillable(n)]
        return min(times) if times else None

    def fill(self, sol: NavSolution, now_s: float, late: bool = False) -> list:
        """The slots that local time ``now_s`` reached without a sample of their own, each message sent
        once with ``sol`` (the newest solution, the one last offered, gated); slots the local clock passed
        over entirely count in ``slots_gap``. Empty when the samples are dense (``next_fill_s`` None)."""
        if self._offered is None:
            return []
        t_fc, t_local = self._offered
        t_fc_now = t_fc + (now_s - t_local)  # the FC's clock, from the newest solution's
        take = {}
        for n in self._enabled:
            if self._fillable(n) and self.slot_index(n, t_fc_now) > self._last_slot[n]:
                self._take(n, self.slot_index(n, t_fc_now))
                self.slots_filled[n] += 1
                take[n] = True
        return self._build(sol, take, late, now_s)

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
        """The messages whose FC-time slot this solution is the first to reach (``sol`` gated, offered in
        sample order; ``now_s``: local monotonic time it was produced, s). ``late``: the solution lags the
        FC's clock beyond CATCH_UP_MAX_LAG_S: its slots are taken, its ODOMETRY is not sent
        (``odometry_late``), the others only within their rate on the local clock (CATCH_UP_MAX_LAG_S);
        what is not sent is counted in ``slots_late``."""
        self.note(sol.time_fc_s, now_s)
        take = {n: True for n in self._enabled if self.due(n, sol.time_fc_s)}
        if not take:
            return []
        self._track_resets(sol)
        return self._build(sol, take, late, now_s)

    def _late_paced(self, name: str, now_s: float) -> bool:
        """A late message may go at local time ``now_s``: at most its rate on the local clock (the slots
        advance by one period, so the mean rate holds under jitter; re-synchronised after a pause)."""
        period = 1.0 / self.rates_hz[name]
        nxt = self._late_next_s[name]
        if nxt is not None and now_s < nxt:
            return False
        self._late_next_s[name] = (now_s if nxt is None or now_s - nxt > period else nxt) + period
        return True

    def _build(self, sol: NavSolution, take: Mapping[str, bool], late: bool, now_s: float) -> list:
        """The messages of the slots in ``take`` that ``sol`` has; with ``late``, ODOMETRY none and the
        others paced on the local clock (``_late_paced``); what is not sent is counted."""
        out: list = []

        def emit(name: str, msg) -> None:
            if not late:
                out.append(msg)
            elif name != "ODOMETRY" and self._late_paced(name, now_s):
                self.slots_behind[name] += 1
                out.append(msg)
            else:
                self.slots_late[name] += 1

        if take.get("ATTITUDE"):
            msg = encode_attitude(sol)
            if msg is not None:
                emit("ATTITUDE", msg)
        if take.get("ATTITUDE_QUATERNION") and sol.heading_valid:
            msg = encode_attitude_quaternion(sol)
            if msg is not None:
                emit("ATTITUDE_QUATERNION", msg)
        if take.get("ODOMETRY") and self.odometry_allowed and heading_usable(sol):
            if late:
                self.odometry_late += 1
            emit("ODOMETRY", encode_odometry(sol, self.profile, self.reset_counter))
        if take.get("NAMED_VALUE_FLOAT"):
            if not late:
                out.extend(encode_named_values(sol))
            elif self._late_paced("NAMED_VALUE_FLOAT", now_s):
                self.slots_behind["NAMED_VALUE_FLOAT"] += 1
                out.extend(encode_named_values(sol))
            else:
                self.slots_late["NAMED_VALUE_FLOAT"] += 1
        return out
