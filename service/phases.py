"""Flight phases: boot -> pre-launch -> launch -> in-flight, from the IMU alone.

- boot: no IMU sample yet.
- pre-launch: at rest on the launcher. The still data is cut into blocks of ``still_seconds``;
  every block that passes the stillness test (estimators.levelling) becomes the current levelling
  and gyro bias, so a vehicle that is handled, then set down, levels on its last still block.
- launch: |specific force| exceeds g by ``detect_accel_m_s2`` for ``detect_hold_s`` (the first
  sample of that run is the launch time). A launch before any still block passed levels on the
  rest data of the current block with relaxed limits (an event says so); with too little data
  the flight starts unlevelled (the attitude filter then levels itself in flight).
- in-flight: the boost is over: the excess has stayed below the threshold for ``detect_hold_s``,
  or ``boost_window_s`` has passed since launch.

Started in flight (a daemon started, or restarted by systemd, while the vehicle flies): before
the first levelling the evidence the daemon has is weighed every sample (``InFlightParams``):
the FC says armed (HEARTBEAT; without a heartbeat, or disarmed, the rule never fires), together
with any of

- the FC's own flying estimate where its HEARTBEAT has one (ArduPlane: MAV_STATE_ACTIVE only
  while is_flying()) for ``hold_s``: the one evidence a smooth level cruise without a pitot has;
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
from dataclasses import dataclass, replace

import numpy as np

from estimators.levelling import (STANDARD_GRAVITY_M_S2, LevellingParams, LevellingResult,
                                  LevellingState, levelling_result, levelling_step)

BOOT, PRE_LAUNCH, LAUNCH, IN_FLIGHT = "boot", "pre-launch", "launch", "in-flight"


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


@dataclass(frozen=True)
class PhaseParams:
    still_seconds: float = 2.0
    detect_accel_m_s2: float = 5.0
    detect_hold_s: float = 0.05
    boost_window_s: float = 1.0
    levelling: LevellingParams = LevellingParams()
    in_flight: InFlightParams = InFlightParams()


@dataclass(frozen=True)
class PhaseState:
    phase: str = BOOT
    block: LevellingState = LevellingState()
    block_start_s: float | None = None
    level: LevellingResult | None = None
    """The last still block's levelling (None until one passed)."""
    level_time_s: float | None = None
    above_since_s: float | None = None
    below_since_s: float | None = None
    launch_time_s: float | None = None
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
    not_still_total_s: float = 0.0
    """Duration of the still blocks since the start that all failed the stillness test (s)."""
    pending_level: LevellingResult | None = None
    """A still block that passed while the rule was still deciding (armed, < decide_s)."""
    block_passed_s: float | None = None
    """Time of the last still block that passed (levelled now or held pending)."""


def _deciding(state: PhaseState, time_s: float, ev: FlightEvidence, params: PhaseParams) -> bool:
    """Armed, not levelled and less than decide_s since the start: a passing block is held."""
    return (ev.armed is True and state.level is None and state.start_time_s is not None
            and time_s - state.start_time_s < params.in_flight.decide_s)


def _level_text(res: LevellingResult) -> str:
    return f"roll {np.degrees(res.roll_rad):.2f} deg, pitch {np.degrees(res.pitch_rad):.2f} deg"


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


def phase_step(state: PhaseState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, time_s: float,
               params: PhaseParams = PhaseParams(), evidence: FlightEvidence | None = None
               ) -> tuple[PhaseState, list[tuple[str, str]]]:
    """One IMU sample. Events are (kind, detail) pairs for the log and the `events` topic.
    ``evidence``: what else the daemon knows (armed, air data) for the started-in-flight rule."""
    events: list[tuple[str, str]] = []
    excess = abs(float(np.linalg.norm(accel_m_s2)) - STANDARD_GRAVITY_M_S2)
    above = excess > params.detect_accel_m_s2
    ev = evidence if evidence is not None else FlightEvidence()

    if state.phase == BOOT:
        state = replace(state, phase=PRE_LAUNCH, block_start_s=time_s, start_time_s=time_s)
        events.append(("phase", PRE_LAUNCH))

    if state.phase == PRE_LAUNCH and state.level is None:
        state, why = _in_flight_evidence(state, excess, time_s, ev, params.in_flight)
        if why:
            state = replace(state, phase=IN_FLIGHT, started_in_flight=True, in_flight_evidence=why,
                            block=LevellingState(), above_since_s=None, pending_level=None)
            events.append(("started_in_flight", why + ": no levelling, no launch"))
            events.append(("phase", IN_FLIGHT))
            return state, events

    if state.phase == PRE_LAUNCH and state.pending_level is not None and not _deciding(state, time_s, ev, params):
        res = state.pending_level  # the decision window is over with no evidence: level on it
        state = replace(state, level=res, level_time_s=time_s, pending_level=None)
        events.append(("levelled", _level_text(res)))

    if state.phase == PRE_LAUNCH:
        if above:
            since = state.above_since_s if state.above_since_s is not None else time_s
            state = replace(state, above_since_s=since)
            if time_s - since >= params.detect_hold_s:
                if state.level is None and state.pending_level is not None:  # no evidence: it launched
                    state = replace(state, level=state.pending_level, level_time_s=time_s, pending_level=None)
                    events.append(("levelled", _level_text(state.level)))
                if state.level is None:
                    # a launch before a full still block: level on what rest data there is, rather
                    # than stay blind for the whole flight (flagged: a short or unsteady rest)
                    res = levelling_result(state.block, replace(params.levelling, min_samples=20,
                                                                 max_accel_std_m_s2=1.0,
                                                                 max_gyro_std_rad_s=0.05))
                    if res.ok:
                        state = replace(state, level=res, level_time_s=time_s)
                        events.append(("levelled", f"on a short rest ({res.samples} samples): roll "
                                       f"{np.degrees(res.roll_rad):.2f} deg, pitch {np.degrees(res.pitch_rad):.2f} deg"))
                    else:
                        events.append(("launch_unlevelled", f"launch before any levelling ({res.reason}); "
                                       "attitude from the attitude filter only"))
                state = replace(state, phase=LAUNCH, launch_time_s=since, below_since_s=None)
                events.append(("phase", LAUNCH))
            return state, events
        state = replace(state, above_since_s=None)
        block = levelling_step(state.block, gyro_rad_s, accel_m_s2)
        start = state.block_start_s if state.block_start_s is not None else time_s
        if time_s - start >= params.still_seconds:
            res = levelling_result(block, params.levelling)
            if state.level is None:  # the started-in-flight rule's stillness evidence
                still_fail = not res.ok and block.n >= params.levelling.min_samples
                state = replace(state, not_still_total_s=state.not_still_total_s + (time_s - start)
                                if still_fail else 0.0)
            if res.ok:
                state = replace(state, block_passed_s=time_s)
                if _deciding(state, time_s, ev, params):  # held until the rule has its evidence
                    state = replace(state, pending_level=res)
                else:
                    if state.level is None:
                        events.append(("levelled", _level_text(res)))
                    state = replace(state, level=res, level_time_s=time_s, pending_level=None)
            else:
                events.append(("not_still", res.reason))
            return replace(state, block=LevellingState(), block_start_s=time_s), events
        return replace(state, block=block), events

    if state.phase == LAUNCH:
        if not above:
            since = state.below_since_s if state.below_since_s is not None else time_s
            state = replace(state, below_since_s=since)
            boost_over = time_s - since >= params.detect_hold_s
        else:
            state = replace(state, below_since_s=None)
            boost_over = False
        if boost_over or time_s - (state.launch_time_s or time_s) >= params.boost_window_s:
            state = replace(state, phase=IN_FLIGHT)
            events.append(("phase", IN_FLIGHT))
        return state, events

    return state, events
