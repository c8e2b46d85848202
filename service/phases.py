"""Flight phases: boot -> pre-launch -> launch -> in-flight, from the IMU and the FC's evidence.

- boot: no IMU sample yet.
- pre-launch: on the ground / on the launcher. The data is cut into blocks of ``still_seconds``;
  a block passes when its MEANS are well known (estimators.levelling: the standard error of the
  mean against the tilt and gyro-bias accuracy, so a vibrating but stationary vehicle levels, at
  any IMU rate >= 20 Hz). The levelling kept is the quietest window: a passing block replaces it
  when its gyro mean is better known, or when its tilt differs beyond the noise (the vehicle was
  moved or set down). Consecutive blocks that fail only for the noise of their means (a
  vibrating vehicle at a low rate) are merged until the longer window levels. Every block says
  why it did or did not level, with its figures.
  ``moved_rad``: the rotation integrated from the bias-corrected gyros since the kept block, so
  the user of the levelling knows when it is stale (a vehicle picked up for a hand launch).
- launch (take-off), per ``vehicle`` (PhaseParams.vehicle), from the evidence a real vehicle gives:
    launcher, hand: | |f| - g | above ``detect_accel_m_s2`` for ``detect_hold_s`` and pointing
        forward (the boost, the throw; an impact points backward or down and is refused);
    runway:  the levelled-frame forward specific force (low-passed, ``filter_tau_s``) above
        ``runway_accel_m_s2`` for ``runway_hold_s`` (the sustained roll);
    multicopter, vtol: the levelled-frame vertical specific force above g by ``liftoff_accel_m_s2``
        for ``liftoff_hold_s`` (the lift-off), or a baro climb above ``liftoff_climb_m_s`` for
        ``in_flight.hold_s``;
  and, for every vehicle, the FC's own landed state going from landed to in the air
  (EXTENDED_SYS_STATE / a log's land detector) for ``in_flight.hold_s``. The launch time is the
  start of the run that decided (the filter's lag ``filter_tau_s`` taken off). While the FC says
  DISARMED nothing is a take-off (a vehicle carried or dropped). A launch before any block
  passed levels on the rest data of the current block with relaxed limits (an event says so);
  with too little data the flight starts unlevelled (the attitude filter levels itself in flight).
- in-flight: launcher/hand: the boost is over (the excess below the threshold for
  ``detect_hold_s``, or ``boost_window_s`` after launch); multicopter/vtol: ``boost_window_s``
  after lift-off; runway: airborne (the FC says in the air or flying, a baro climb; an airspeed
  is no evidence: the roll reaches it on the ground) or ``runway_max_roll_s`` after the roll began.

Started in flight (a daemon started, or restarted by systemd, while the vehicle flies): before
the first levelling the evidence the daemon has is weighed every sample (``InFlightParams``):
the FC says armed (HEARTBEAT; without a heartbeat, or disarmed, the rule never fires), together
with any of

- the FC's own flying estimate where its HEARTBEAT has one (ArduPlane: MAV_STATE_ACTIVE only
  while is_flying()) for ``hold_s``: the one evidence a smooth level cruise without a pitot has;
- the FC's own landed state saying "in the air" for ``hold_s`` when it was never seen landed in
  this run (seen landed first, the change is a take-off);
- airspeed (differential pressure) above ``airspeed_m_s`` for ``hold_s``;
- |baro altitude rate| above ``alt_rate_m_s`` for ``hold_s`` (once the rate filter has settled);
- the IMU not still: every still block since the start failed the stillness test, for at least
  ``not_still_s`` (blocks that failed only for too few samples do not count);
- | |f| - g | above ``accel_norm_m_s2`` for ``accel_norm_hold_s`` (a sustained turn or pull-up;
  a launch boost beyond ``detect_accel_m_s2`` is a launch, decided by the rule below).

Then the phase goes straight to in-flight with ``started_in_flight`` set and an event naming the
evidence: no levelling, no launch. While the FC says armed, a still block that passes before
``decide_s`` after the start is held (``pending_level``) and levels only when ``decide_s`` has
passed without evidence (or a launch comes first): the altitude rate needs ~3 s to settle, then
``hold_s``, so a steady climb cannot level before its evidence is in. A vehicle armed and still on its launcher has none of the
evidence and levels as before (the normal launch). A launch detected before any levelling is
a launch unless the evidence was already in at that sample.

Pure: ``phase_step(state, gyro_rad_s, accel_m_s2, time_s, params, evidence) -> (state, events)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace as dc_replace

import numpy as np

from estimators.records import fast_replace as replace
from estimators.levelling import (STANDARD_GRAVITY_M_S2, LevellingParams, LevellingResult,
                                  LevellingState, levelling_merge, levelling_result, levelling_step)

BOOT, PRE_LAUNCH, LAUNCH, IN_FLIGHT = "boot", "pre-launch", "launch", "in-flight"
VEHICLES = ("launcher", "hand", "runway", "multicopter", "vtol")
"""How the vehicle leaves the ground (PhaseParams.vehicle)."""
IMPULSE_VEHICLES = ("launcher", "hand")
"""Vehicles whose take-off is a short hard push along the flight axis."""


@dataclass(frozen=True)
class InFlightParams:
    """The "started in flight" rule (module docstring). Units in the names."""

    airspeed_m_s: float = 12.0
    """True airspeed above this (with armed) means flying (m/s). Set it above the strongest wind
    the launcher sees: a pitot facing a 12 m/s wind on the launcher reads 12 m/s."""
    alt_rate_m_s: float = 1.5
    """|Baro altitude rate| above this (with armed) means flying (m/s)."""
    hold_s: float = 1.0
    """Airspeed / altitude rate must stay above their thresholds this long (s): one gust is not
    a flight."""
    not_still_s: float = 4.0
    """Still blocks failing the stillness test back to back since the start for this long (s)."""
    accel_norm_m_s2: float = 2.0
    """| |f| - g | above this ... (m/s^2)"""
    accel_norm_hold_s: float = 1.0
    """... for this long (s) means flying."""
    decide_s: float = 4.5
    """While armed, a passing still block levels no earlier than this after the start (s): the altitude
    rate settles 3 s after the first pressure sample (air_data: 3 T) and must then hold
    ``hold_s``."""
    fc_tilt_sigma_rad: float = math.radians(1.0)
    """1-sigma roll/pitch given to the attitude filter initialised in flight from a trusted FC
    ATTITUDE (the FC's normal tilt error, with margin for the sample's age)."""
    accel_tilt_sigma_rad: float = math.radians(20.0)
    """1-sigma roll/pitch given to the attitude filter initialised in flight from the
    accelerometer (in a turn the specific force is not gravity: the bank angle is the error)."""
    gyro_bias_sigma_rad_s: float = math.radians(0.2)
    """1-sigma gyro bias (per axis, zero mean) given to the attitude filter initialised in flight.
    No rest measured it, but the stream is the FC's calibrated gyro (ArduPilot and PX4 remove the
    offset at boot): what is left is the in-run drift since, ~0.2 deg/s (the simulator's consumer
    gyro: 0.2; ArduPlane SITL 0.01-0.14 over a flight; ArduCopter EKF3's own estimate on the real
    RTL log: 0.25 on y). C's built-in 0.5 deg/s (a raw sensor's turn-on bias) let the first
    sustained accelerations of a run started on the take-off roll go into the bias: 1.1 / 0.4 /
    -3.7 deg/s and a roll error of -20 deg for 20 s on an ArduPlane SITL log
    (bench/started_in_flight_logs.py). Only for a stream of at least ``calibrated_gyro_min_rate_hz``."""
    calibrated_gyro_min_rate_hz: float = 40.0
    """The prior above holds for an IMU stream whose samples resolve the FC's low-passed gyro: at
    least twice its cutoff (ArduPilot's INS_GYRO_FILTER, 20 Hz by default: 40 Hz; PX4's
    IMU_GYRO_CUTOFF 40 Hz would ask 80, its logs carry >= 100 Hz). A slower stream's samples are
    instants of that rate, aliased: their integration has an error of its own that no calibration
    bounds, and C's bias state must stay free to take it (its built-in turn-on prior). Measured on
    the real ArduCopter RTL log (25 Hz, INS_GYRO_FILTER 20): with EKF3's own bias estimate and a
    tight prior C's roll error grew ~1 deg/s in the hover while the accelerometer agreed with the
    FC within 0.7 deg (roll RMS 2.51 -> 3.68 deg)."""

    def __post_init__(self) -> None:
        for name, v in self.__dict__.items():
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class FlightEvidence:
    """What the daemon knows besides the IMU, at the sample's time. None = unknown."""

    armed: bool | None = None
    """The FC's last HEARTBEAT says armed."""
    airspeed_m_s: float | None = None
    """True airspeed from the differential pressure (None: no pitot, or no fresh sample)."""
    alt_rate_m_s: float | None = None
    """Baro altitude rate (None: not settled yet or no fresh sample)."""
    fc_reports_flying: bool | None = None
    """The FC's own flying estimate, where its HEARTBEAT carries one: ArduPlane sends
    MAV_STATE_ACTIVE only while its is_flying() says so (STANDBY when armed on the ground; CRITICAL
    and EMERGENCY say nothing either way: None). None for autopilots whose ACTIVE means armed."""
    fc_landed: bool | None = None
    """The FC's own landed state (EXTENDED_SYS_STATE, a log's land detector): True on the ground,
    False in the air; None where the FC does not say (mavlink_io.samples.FcFlightState)."""


_NO_EVIDENCE = FlightEvidence()
"""Nothing known besides the IMU (a frozen record, shared: not built again per sample)."""


@dataclass(frozen=True)
class PhaseParams:
    still_seconds: float = 2.0
    detect_accel_m_s2: float = 5.0
    detect_hold_s: float = 0.05
    boost_window_s: float = 1.0
    levelling: LevellingParams = LevellingParams()
    in_flight: InFlightParams = InFlightParams()
    vehicle: str | None = "launcher"
    """launcher | hand | runway | multicopter | vtol (module docstring); None: not known yet
    (``[launch] vehicle = "auto"`` before the FC's HEARTBEAT, service/vehicle_type.py): levelling
    goes on, no take-off is declared."""
    forward_sensor: tuple = (1.0, 0.0, 0.0)
    """The body x axis (the flight axis) in sensor axes, from the configured mount."""
    detect_started_in_flight: bool = True
    """Weigh the started-in-flight rule (config launch.in_flight_start_detect)."""
    filter_tau_s: float = 0.2
    """Low-pass time constant of the specific force the runway and lift-off rules judge (s):
    averages out the motor vibration (0.06 of a 13 Hz vibration's amplitude)."""
    runway_accel_m_s2: float = 1.5
    """Runway: forward specific force (levelled frame) that means the take-off roll (a full-throttle
    roll gives 2-4 m/s^2; taxiing starts and stops stay below) ..."""
    runway_hold_s: float = 1.0
    """... held this long (s): a taxi jolt is shorter."""
    runway_max_roll_s: float = 60.0
    """Runway: in-flight at the latest this long after the roll began (s)."""
    liftoff_accel_m_s2: float = 0.8
    """Multicopter/VTOL: vertical specific force above g by this means lift-off ..."""
    liftoff_hold_s: float = 0.3
    """... held this long (s)."""
    liftoff_climb_m_s: float = 0.7
    """Multicopter/VTOL: a baro climb rate above this for in_flight.hold_s means lift-off (m/s)."""
    impulse_forward_share: float = 0.5
    """Launcher/hand: the boost's excess specific force must point forward: its component along
    the flight axis at least this share of its magnitude (an impact points backward or down)."""
    moved_rad: float = math.radians(2.0)
    """Rotation since the kept levelling block above which the levelling is stale (rad)."""

    def __post_init__(self) -> None:
        if self.vehicle is not None and self.vehicle not in VEHICLES:
            raise ValueError(f"vehicle must be one of {VEHICLES} or None, got {self.vehicle!r}")
        fwd = np.asarray(self.forward_sensor, float)
        if fwd.shape != (3,) or not np.all(np.isfinite(fwd)) or abs(np.linalg.norm(fwd) - 1.0) > 1e-6:
            raise ValueError(f"forward_sensor must be a unit 3-vector, got {self.forward_sensor!r}")
        for name in ("still_seconds", "boost_window_s", "filter_tau_s", "runway_accel_m_s2", "runway_hold_s",
                     "runway_max_roll_s", "liftoff_accel_m_s2", "liftoff_hold_s", "liftoff_climb_m_s",
                     "impulse_forward_share", "moved_rad"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class PhaseState:
    phase: str = BOOT
    block: LevellingState = LevellingState()
    block_start_s: float | None = None
    level: LevellingResult | None = None
    """The kept levelling (the quietest passing block; None until one passed)."""
    level_block: LevellingState | None = None
    """The samples of the kept levelling (what method A levels on)."""
    level_time_s: float | None = None
    above_since_s: float | None = None
    below_since_s: float | None = None
    launch_time_s: float | None = None
    launch_evidence: str = ""
    """What decided the take-off (one line)."""
    start_time_s: float | None = None
    """Time of the first sample."""
    started_in_flight: bool = False
    """The daemon started while the vehicle flew: no levelling, no launch (module docstring)."""
    in_flight_evidence: str = ""
    # evidence bookkeeping of the started-in-flight rule (before the first levelling)
    airspeed_since_s: float | None = None
    fc_flying_since_s: float | None = None
    alt_rate_since_s: float | None = None
    accel_norm_since_s: float | None = None
    fc_air_since_s: float | None = None
    """The FC says in the air (fc_landed False) since."""
    fc_seen_landed: bool = False
    """The FC said landed at some point of this run."""
    not_still_total_s: float = 0.0
    """Duration of the still blocks since the start that all failed the stillness test (s)."""
    pending_level: LevellingResult | None = None
    """A still block that passed while the rule was still deciding (armed, < decide_s)."""
    pending_block: LevellingState | None = None
    noisy_run: LevellingState = LevellingState()
    """Consecutive blocks that failed only for the noise of their means, merged (a vibrating
    vehicle levels on the longer window; reset by any other verdict)."""
    block_passed_s: float | None = None
    """Time of the last still block that passed (levelled now or held pending)."""
    last_block_mean_m_s2: np.ndarray | None = None
    """Mean specific force of the last completed block (the reference before any levelling)."""
    # take-off detection
    time_prev_s: float | None = None
    f_lp_m_s2: tuple | None = None
    """Low-passed specific force (filter_tau_s), sensor axes (3 floats)."""
    run_since_s: float | None = None
    """Start of the current run of the runway / lift-off condition."""
    climb_since_s: float | None = None
    impulse_sum_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Sum of the excess specific force over the current launcher/hand run."""
    impulse_refused: bool = False
    disarmed_refused: bool = False
    # staleness of the levelling
    moved_vec_rad: tuple = (0.0, 0.0, 0.0)
    moved_rad: float = 0.0
    """Largest rotation (rad) integrated since the kept levelling block ended."""


def _deciding(state: PhaseState, time_s: float, ev: FlightEvidence, params: PhaseParams) -> bool:
    """Armed, not levelled and less than decide_s since the start: a passing block is held."""
    return (ev.armed is True and state.level is None and state.start_time_s is not None
            and time_s - state.start_time_s < params.in_flight.decide_s)


def _level_text(res: LevellingResult) -> str:
    return (f"roll {np.degrees(res.roll_rad):.2f} deg, pitch {np.degrees(res.pitch_rad):.2f} deg "
            f"({res.figures()})")


def _in_flight_evidence(state: PhaseState, excess_m_s2: float, time_s: float, ev: FlightEvidence,
                        p: InFlightParams) -> tuple[PhaseState, str]:
    """Update the evidence timers; return the evidence that the vehicle flies ("" = none)."""
    def since(prev, cond):
        return (prev if prev is not None else time_s) if cond else None
    state = replace(
        state,
        airspeed_since_s=since(state.airspeed_since_s, ev.airspeed_m_s is not None and ev.airspeed_m_s > p.airspeed_m_s),
        fc_flying_since_s=since(state.fc_flying_since_s, ev.fc_reports_flying is True),
        alt_rate_since_s=since(state.alt_rate_since_s, ev.alt_rate_m_s is not None and abs(ev.alt_rate_m_s) > p.alt_rate_m_s),
        accel_norm_since_s=since(state.accel_norm_since_s, excess_m_s2 > p.accel_norm_m_s2))
    if ev.armed is not True:
        return state, ""
    found = []
    if state.fc_flying_since_s is not None and time_s - state.fc_flying_since_s >= p.hold_s:
        found.append("the FC reports flying (HEARTBEAT MAV_STATE_ACTIVE from ArduPlane)")
    if not state.fc_seen_landed and state.fc_air_since_s is not None and time_s - state.fc_air_since_s >= p.hold_s:
        found.append("the FC reports in the air (landed state)")
    if state.airspeed_since_s is not None and time_s - state.airspeed_since_s >= p.hold_s:
        found.append(f"airspeed {ev.airspeed_m_s:.1f} m/s > {p.airspeed_m_s:g} m/s")
    if state.alt_rate_since_s is not None and time_s - state.alt_rate_since_s >= p.hold_s:
        found.append(f"baro altitude rate {ev.alt_rate_m_s:+.1f} m/s beyond {p.alt_rate_m_s:g} m/s")
    if state.not_still_total_s >= p.not_still_s:
        found.append(f"IMU not still for {state.not_still_total_s:.1f} s")
    if state.accel_norm_since_s is not None and time_s - state.accel_norm_since_s >= p.accel_norm_hold_s:
        found.append(f"| |f| - g | = {excess_m_s2:.1f} m/s^2 > {p.accel_norm_m_s2:g} m/s^2 "
                     f"for {time_s - state.accel_norm_since_s:.1f} s")
    return state, ("FC armed, " + ", ".join(found)) if found else ""


def _track(state: PhaseState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, time_s: float,
           ev: FlightEvidence, params: PhaseParams) -> PhaseState:
    """Per-sample bookkeeping: the low-passed specific force, the FC's landed state, the rotation
    since the kept levelling block. On Python floats (the per-sample path)."""
    dt = time_s - state.time_prev_s if state.time_prev_s is not None else 0.0
    f = accel_m_s2.tolist()
    if state.f_lp_m_s2 is None or not (0.0 < dt < 1.0):
        f_lp = tuple(f)
    else:  # first-order low-pass, a = dt / (tau + dt)
        a = dt / (params.filter_tau_s + dt)
        f_lp = tuple(y + (x - y) * a for x, y in zip(f, state.f_lp_m_s2))
    seen = state.fc_seen_landed or ev.fc_landed is True
    air = (state.fc_air_since_s if state.fc_air_since_s is not None else time_s) if ev.fc_landed is False else None
    moved_vec, moved = state.moved_vec_rad, state.moved_rad
    if state.level is not None and 0.0 < dt < 1.0:
        # small-angle sum of the bias-corrected rotation (exact enough for a staleness test)
        bias = state.level.gyro_bias_rad_s
        moved_vec = tuple(m + (w - b) * dt for m, w, b in zip(moved_vec, gyro_rad_s.tolist(), bias.tolist()))
        moved = max(moved, math.sqrt(sum(x * x for x in moved_vec)))
    return replace(state, time_prev_s=time_s, f_lp_m_s2=f_lp, fc_seen_landed=seen, fc_air_since_s=air,
                   moved_vec_rad=moved_vec, moved_rad=moved)


def _reference_f(state: PhaseState) -> np.ndarray | None:
    """The specific force at rest: the levelling's mean, else the last completed block's."""
    if state.level is not None:
        return state.level.accel_mean_m_s2
    return state.last_block_mean_m_s2


def _sustained_takeoff(state: PhaseState, time_s: float, ev: FlightEvidence, params: PhaseParams
                       ) -> tuple[PhaseState, float | None, str]:
    """Runway roll / lift-off from the low-passed specific force in the levelled frame, the baro
    climb (multicopter, vtol). Returns (state, launch time or None, evidence)."""
    ref = _reference_f(state)
    launch, why = None, ""
    if ref is not None and state.f_lp_m_s2 is not None:
        g_ref = float(np.linalg.norm(ref))
        up = ref / g_ref  # at rest f = -g * down: f points up
        d = np.array(state.f_lp_m_s2) - ref
        vert = float(d @ up)
        if params.vehicle == "runway":
            fwd = np.asarray(params.forward_sensor, float)
            fwd_h = fwd - (fwd @ up) * up
            nh = float(np.linalg.norm(fwd_h))
            value = float(d @ fwd_h) / nh if nh > 0.1 else 0.0
            thr, hold, what = params.runway_accel_m_s2, params.runway_hold_s, "forward"
        else:
            value, thr, hold, what = vert, params.liftoff_accel_m_s2, params.liftoff_hold_s, "vertical"
        run = (state.run_since_s if state.run_since_s is not None else time_s) if value > thr else None
        state = replace(state, run_since_s=run)
        if run is not None and time_s - run >= hold:
            launch = run - params.filter_tau_s  # the low-pass crossed its threshold about tau late
            why = f"{what} specific force {value:+.1f} m/s^2 > {thr:g} m/s^2 for {time_s - run:.1f} s"
    if launch is None and params.vehicle in ("multicopter", "vtol"):
        climbing = ev.alt_rate_m_s is not None and ev.alt_rate_m_s > params.liftoff_climb_m_s
        since = (state.climb_since_s if state.climb_since_s is not None else time_s) if climbing else None
        state = replace(state, climb_since_s=since)
        if since is not None and time_s - since >= params.in_flight.hold_s:
            launch = since
            why = f"baro climb {ev.alt_rate_m_s:+.1f} m/s > {params.liftoff_climb_m_s:g} m/s"
    return state, launch, why


def _impulse_takeoff(state: PhaseState, accel_m_s2: np.ndarray, excess: float, time_s: float,
                     params: PhaseParams) -> tuple[PhaseState, float | None, str, list]:
    """Launcher boost / hand throw: | |f| - g | above the threshold for detect_hold_s, pointing
    forward. Returns (state, launch time or None, evidence, events)."""
    events = []
    if excess <= params.detect_accel_m_s2:
        if state.above_since_s is not None or state.impulse_refused:
            state = replace(state, above_since_s=None, impulse_sum_m_s2=np.zeros(3), impulse_refused=False)
        return state, None, "", events
    since = state.above_since_s if state.above_since_s is not None else time_s
    ref = _reference_f(state)
    f = np.asarray(accel_m_s2, float)
    push = state.impulse_sum_m_s2 + (f - ref if ref is not None else f)
    state = replace(state, above_since_s=since, impulse_sum_m_s2=push)
    if time_s - since < params.detect_hold_s or state.impulse_refused:
        return state, None, "", events
    n = float(np.linalg.norm(push))
    share = float(push @ np.asarray(params.forward_sensor, float)) / n if n > 0 else 0.0
    if share < params.impulse_forward_share:
        events.append(("takeoff_refused", f"specific-force spike |f| = {np.linalg.norm(f):.0f} m/s^2 pointing "
                       f"{'backward' if share < 0 else 'off the flight axis'} (forward share {share:+.2f}): "
                       "not a take-off (an impact, a knock or a pick-up)"))
        return replace(state, impulse_refused=True), None, "", events
    return state, since, f"| |f| - g | {excess:.1f} m/s^2 > {params.detect_accel_m_s2:g} m/s^2 forward", events


def _take_level(state: PhaseState, res: LevellingResult, block: LevellingState, time_s: float
                ) -> tuple[PhaseState, list]:
    """A passing block against the kept levelling: keep the quietest, unless the vehicle moved."""
    events = []
    cur = state.level
    if cur is None:
        events.append(("levelled", _level_text(res)))
        return replace(state, level=res, level_block=block, level_time_s=time_s, pending_level=None,
                       pending_block=None, moved_vec_rad=(0.0, 0.0, 0.0), moved_rad=0.0), events
    a, b = cur.accel_mean_m_s2, res.accel_mean_m_s2
    tilt_change = math.acos(max(-1.0, min(1.0, float(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b)))))
    noise = math.hypot(cur.tilt_noise_rad, res.tilt_noise_rad)
    if tilt_change > 3.0 * noise + math.radians(0.05):  # moved or set down: the new attitude counts
        events.append(("levelled", f"again, the tilt changed by {math.degrees(tilt_change):.2f} deg: "
                       + _level_text(res)))
    elif not res.gyro_bias_sigma_rad_s < cur.gyro_bias_sigma_rad_s:  # same attitude, noisier: keep
        return replace(state, moved_vec_rad=(0.0, 0.0, 0.0), moved_rad=0.0), events
    return replace(state, level=res, level_block=block, level_time_s=time_s, pending_level=None,
                   pending_block=None, moved_vec_rad=(0.0, 0.0, 0.0), moved_rad=0.0), events


def phase_step(state: PhaseState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, time_s: float,
               params: PhaseParams = PhaseParams(), evidence: FlightEvidence | None = None
               ) -> tuple[PhaseState, list[tuple[str, str]]]:
    """One IMU sample. Events are (kind, detail) pairs for the log and the `events` topic.
    ``evidence``: what else the daemon knows (armed, air data, the FC's landed state)."""
    events: list[tuple[str, str]] = []
    ax, ay, az = accel_m_s2.tolist()
    excess = abs(math.sqrt(ax * ax + ay * ay + az * az) - STANDARD_GRAVITY_M_S2)
    above = excess > params.detect_accel_m_s2
    ev = evidence if evidence is not None else _NO_EVIDENCE
    impulse = params.vehicle in IMPULSE_VEHICLES

    if state.phase == BOOT:
        state = replace(state, phase=PRE_LAUNCH, block_start_s=time_s, start_time_s=time_s)
        events.append(("phase", PRE_LAUNCH))
    if state.phase in (PRE_LAUNCH, LAUNCH):
        state = _track(state, gyro_rad_s, accel_m_s2, time_s, ev, params)

    if state.phase == PRE_LAUNCH and state.level is None and params.detect_started_in_flight:
        state, why = _in_flight_evidence(state, excess, time_s, ev, params.in_flight)
        if why:
            state = replace(state, phase=IN_FLIGHT, started_in_flight=True, in_flight_evidence=why,
                            block=LevellingState(), above_since_s=None, pending_level=None, pending_block=None)
            events.append(("started_in_flight", why + ": no levelling, no launch"))
            events.append(("phase", IN_FLIGHT))
            return state, events

    if state.phase == PRE_LAUNCH and state.pending_level is not None and not _deciding(state, time_s, ev, params):
        # the decision window is over with no evidence: level on it
        state, lev_events = _take_level(state, state.pending_level, state.pending_block, time_s)
        events += lev_events

    if state.phase == PRE_LAUNCH:
        if params.vehicle is None:  # the take-off model is not known yet: nothing is declared
            launch, why, imp_events = None, "", []
        elif impulse:
            state, launch, why, imp_events = _impulse_takeoff(state, accel_m_s2, excess, time_s, params)
        else:
            state, launch, why = _sustained_takeoff(state, time_s, ev, params)
            imp_events = []
        events += imp_events
        if launch is None and params.vehicle is not None and state.fc_seen_landed and state.fc_air_since_s is not None \
                and time_s - state.fc_air_since_s >= params.in_flight.hold_s:
            launch, why = state.fc_air_since_s, "the FC reports in the air after landed (landed state)"
        if launch is not None and ev.armed is False:
            if not state.disarmed_refused:
                events.append(("takeoff_refused", f"{why} while the FC says disarmed: not a take-off"))
            state, launch = replace(state, disarmed_refused=True), None
        if launch is not None:
            return _launch(state, launch, why, time_s, params, events)
        if impulse and above:
            return state, events  # a spike sample is neither rest data nor a launch yet
        block = levelling_step(state.block, gyro_rad_s, accel_m_s2, time_s, params.levelling.batch_s)
        start = state.block_start_s if state.block_start_s is not None else time_s
        if time_s - start >= params.still_seconds:
            res = levelling_result(block, params.levelling)
            state = replace(state, last_block_mean_m_s2=block.accel_mean_m_s2.copy())
            if state.level is None:  # the started-in-flight rule's stillness evidence
                lp = params.levelling  # a mean uncertain beyond 3x the accuracy is motion, not vibration
                moving = not res.noisy or res.tilt_noise_rad > 3 * lp.max_tilt_noise_rad \
                    or res.gyro_bias_sigma_rad_s > 3 * lp.max_gyro_sem_rad_s
                still_fail = not res.ok and block.n >= lp.min_samples and moving
                state = replace(state, not_still_total_s=state.not_still_total_s + (time_s - start)
                                if still_fail else 0.0)
            if res.noisy:  # vibrating: try the longer window of the consecutive noisy blocks
                merged = levelling_merge(state.noisy_run, block)
                res_m = levelling_result(merged, params.levelling)
                state = replace(state, noisy_run=merged if res_m.noisy else LevellingState())
                if res_m.ok or not res_m.noisy:
                    res, block = res_m, merged
            elif state.noisy_run.n:
                state = replace(state, noisy_run=LevellingState())
            if res.ok:
                state = replace(state, block_passed_s=time_s)
                if _deciding(state, time_s, ev, params):  # held until the rule has its evidence
                    state = replace(state, pending_level=res, pending_block=block)
                else:
                    state, lev_events = _take_level(state, res, block, time_s)
                    events += lev_events
            else:
                figs = f" ({res.figures()})" if math.isfinite(res.accel_std_m_s2) else ""  # else the reason has them
                events.append(("not_still", res.reason + figs))
            return replace(state, block=LevellingState(), block_start_s=time_s), events
        return replace(state, block=block), events

    if state.phase == LAUNCH:
        over = False
        if impulse:
            if not above:
                since = state.below_since_s if state.below_since_s is not None else time_s
                state = replace(state, below_since_s=since)
                over = time_s - since >= params.detect_hold_s
            else:
                state = replace(state, below_since_s=None)
            over = over or time_s - state.launch_time_s >= params.boost_window_s
        elif params.vehicle == "runway":
            p = params.in_flight
            if ev.fc_landed is False or ev.fc_reports_flying is True:
                over = "the FC reports in the air"
            elif ev.alt_rate_m_s is not None and ev.alt_rate_m_s > p.alt_rate_m_s:
                over = f"baro climb {ev.alt_rate_m_s:+.1f} m/s"
            elif time_s - state.launch_time_s >= params.runway_max_roll_s:
                over = f"{params.runway_max_roll_s:g} s after the roll began"
            if over:
                events.append(("airborne", f"{over}, {time_s - state.launch_time_s:.1f} s after the roll began"))
        else:
            over = time_s - state.launch_time_s >= params.boost_window_s
        if over:
            state = replace(state, phase=IN_FLIGHT)
            events.append(("phase", IN_FLIGHT))
        return state, events

    return state, events


def _launch(state: PhaseState, launch_s: float, why: str, time_s: float, params: PhaseParams,
            events: list) -> tuple[PhaseState, list]:
    """Take-off decided at ``launch_s``: level on what there is, then the launch phase."""
    if state.level is None and state.pending_level is not None:  # no evidence: it launched
        state, lev_events = _take_level(state, state.pending_level, state.pending_block, time_s)
        events += lev_events
    if state.level is None:
        # a launch before a full still block: level on what rest data there is, rather than stay
        # blind for the whole flight (flagged: a short or unsteady rest)
        res = levelling_result(state.block, dc_replace(params.levelling, min_samples=20, min_duration_s=0.3))
        if res.ok:
            state = replace(state, level=res, level_block=state.block, level_time_s=time_s)
            events.append(("levelled", f"on a short rest: {_level_text(res)}"))
        else:
            events.append(("launch_unlevelled", f"launch before any levelling ({res.reason}); "
                           "attitude from the attitude filter only"))
    state = replace(state, phase=LAUNCH, launch_time_s=launch_s, launch_evidence=why, below_since_s=None)
    events.append(("takeoff", f"{params.vehicle}: {why}, at {launch_s:.2f} s"))
    events.append(("phase", LAUNCH))
    return state, events
