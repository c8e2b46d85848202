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

Pure: ``phase_step(state, gyro_rad_s, accel_m_s2, time_s, params) -> (state, events)``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimators.levelling import (STANDARD_GRAVITY_M_S2, LevellingParams, LevellingResult,
                                  LevellingState, levelling_result, levelling_step)

BOOT, PRE_LAUNCH, LAUNCH, IN_FLIGHT = "boot", "pre-launch", "launch", "in-flight"


@dataclass(frozen=True)
class PhaseParams:
    still_seconds: float = 2.0
    detect_accel_m_s2: float = 5.0
    detect_hold_s: float = 0.05
    boost_window_s: float = 1.0
    levelling: LevellingParams = LevellingParams()


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


def phase_step(state: PhaseState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray, time_s: float,
               params: PhaseParams = PhaseParams()) -> tuple[PhaseState, list[tuple[str, str]]]:
    """One IMU sample. Events are (kind, detail) pairs for the log and the `events` topic."""
    events: list[tuple[str, str]] = []
    excess = abs(float(np.linalg.norm(accel_m_s2)) - STANDARD_GRAVITY_M_S2)
    above = excess > params.detect_accel_m_s2

    if state.phase == BOOT:
        state = replace(state, phase=PRE_LAUNCH, block_start_s=time_s)
        events.append(("phase", PRE_LAUNCH))

    if state.phase == PRE_LAUNCH:
        if above:
            since = state.above_since_s if state.above_since_s is not None else time_s
            state = replace(state, above_since_s=since)
            if time_s - since >= params.detect_hold_s:
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
            if res.ok:
                if state.level is None:
                    events.append(("levelled", f"roll {np.degrees(res.roll_rad):.2f} deg, pitch {np.degrees(res.pitch_rad):.2f} deg"))
                state = replace(state, level=res, level_time_s=time_s)
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
