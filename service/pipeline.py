"""The estimator wiring: typed samples in, NavSolution out. No sockets, no clocks.

The daemon (service/daemon.py) and the offline replay feed the same Pipeline, so what a user
replays is what flies. Each ``on_*`` method takes one decoded sample; ``on_imu`` returns the
NavSolution for that sample (None while there is nothing to say).

What runs now:
- phases (service/phases.py): levelling and gyro bias at rest, launch detection;
- attitude: the levelled attitude before launch, then coning-correct quaternion strapdown of the
  bias-corrected gyros (estimators/strapdown.py) from the levelled start. Its yaw is arbitrary
  (0 at launch) until a heading source exists, so ``heading_valid`` stays False.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from estimators.rotations import (dcm_from_quat, euler_from_quat, quat_conj, quat_from_euler,
                                  quat_mul)
from estimators.levelling import LevellingParams
from estimators.strapdown import StrapdownParams, StrapdownState, strapdown_init, strapdown_step
from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
from service.phases import IN_FLIGHT, LAUNCH, PRE_LAUNCH, PhaseParams, PhaseState, phase_step
from service.solution import NavSolution

log = logging.getLogger("azimuthd.pipeline")


@dataclass
class PipelineCounters:
    imu_samples: int = 0
    imu_rejected: int = 0
    pressure_samples: int = 0
    fc_attitude_samples: int = 0
    strapdown_gaps: int = 0
    reasons: dict = field(default_factory=dict)

    def reject(self, reason: str) -> None:
        self.imu_rejected += 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1


class Pipeline:
    """Holds the estimator states; every update is a pure step on them."""

    def __init__(self, cfg: dict):
        self.cfg = cfg
        imu = cfg["imu"]
        launch = cfg["launch"]
        self.gyro_bias_sigma_rad_s = math.radians(imu["gyro_bias_sigma_deg_s"])
        self.phase_params = PhaseParams(still_seconds=imu["still_seconds"],
                                        levelling=LevellingParams(accel_bias_sigma_m_s2=imu["accel_bias_sigma_m_s2"]),
                                        detect_accel_m_s2=launch["detect_accel_m_s2"],
                                        detect_hold_s=launch["detect_hold_s"],
                                        boost_window_s=launch["boost_window_s"])
        self.strapdown_params = StrapdownParams(max_dt_s=cfg["mavlink"]["imu_gap_s"])
        # q_body_from_sensor: the sensor axes' attitude in the body frame (configured mount)
        self.q_body_from_sensor = quat_from_euler(math.radians(imu["mount_roll_deg"]),
                                                  math.radians(imu["mount_pitch_deg"]),
                                                  math.radians(imu["mount_yaw_deg"]))
        self.q_sensor_from_body = quat_conj(self.q_body_from_sensor)
        self.phase = PhaseState()
        self.strapdown: StrapdownState | None = None
        self.gyro_bias_rad_s = np.zeros(3)
        self.counters = PipelineCounters()
        self.events: list[tuple[str, str]] = []
        self.last_time_fc_s: float | None = None
        self.fc_attitude: FcAttitude | None = None
        self.pressure: PressureSample | None = None

    # --- inputs -------------------------------------------------------------------------------

    def on_imu(self, s: ImuSample) -> NavSolution | None:
        if not (np.all(np.isfinite(s.gyro_rad_s)) and np.all(np.isfinite(s.accel_m_s2))
                and math.isfinite(s.time_fc_s)):
            self.counters.reject("non-finite IMU sample")
            return None
        if self.last_time_fc_s is not None and s.time_fc_s <= self.last_time_fc_s:
            self.counters.reject("IMU time not increasing")
            return None
        self.last_time_fc_s = s.time_fc_s
        self.counters.imu_samples += 1

        prev_phase = self.phase.phase
        self.phase, events = phase_step(self.phase, s.gyro_rad_s, s.accel_m_s2, s.time_fc_s,
                                        self.phase_params)
        for ev in events:
            self._event(*ev)
        if prev_phase == PRE_LAUNCH and self.phase.phase == LAUNCH:
            self._start_flight(s)
        elif self.phase.phase in (LAUNCH, IN_FLIGHT) and self.strapdown is not None:
            self.strapdown, diag = strapdown_step(self.strapdown, s.gyro_rad_s - self.gyro_bias_rad_s,
                                                  s.time_fc_s, self.strapdown_params)
            if not diag.integrated and diag.reason not in ("first sample",):
                self.counters.strapdown_gaps += 1
                self._event("strapdown", diag.reason)
        return self._solution(s)

    def on_pressure(self, s: PressureSample) -> None:
        self.pressure = s
        self.counters.pressure_samples += 1

    def on_fc_attitude(self, a: FcAttitude) -> None:
        self.fc_attitude = a
        self.counters.fc_attitude_samples += 1

    def on_fc_reboot(self) -> None:
        """The FC clock restarted: keep the attitude, restart the time bookkeeping."""
        self.last_time_fc_s = None
        if self.strapdown is not None:
            self.strapdown = StrapdownState(self.strapdown.q_ref_from_sensor)
        self._event("fc_reboot", "FC time restarted; integration resumes at the next sample")

    def drain_events(self) -> list[tuple[str, str]]:
        ev, self.events = self.events, []
        return ev

    # --- internals ----------------------------------------------------------------------------

    def _event(self, kind: str, detail: str) -> None:
        self.events.append((kind, detail))

    def _start_flight(self, s: ImuSample) -> None:
        level = self.phase.level
        self.gyro_bias_rad_s = level.gyro_bias_rad_s.copy()
        # yaw unknown at launch: 0 until a heading source exists
        q_nav_from_sensor = quat_from_euler(level.roll_rad, level.pitch_rad, 0.0)
        self.strapdown = strapdown_init(q_nav_from_sensor)
        self.strapdown, _ = strapdown_step(self.strapdown, s.gyro_rad_s - self.gyro_bias_rad_s,
                                           s.time_fc_s, self.strapdown_params)

    def _q_nav_from_sensor(self) -> np.ndarray | None:
        if self.strapdown is not None:
            return self.strapdown.q_ref_from_sensor
        level = self.phase.level
        if level is not None:
            return quat_from_euler(level.roll_rad, level.pitch_rad, 0.0)
        return None

    def _tilt_sigma_rad(self, time_s: float) -> float | None:
        """1-sigma roll/pitch: levelling error, then growing with the residual gyro bias.

        The bias left after levelling is ``imu.gyro_bias_sigma_deg_s`` (the turn-on bias is gone,
        in-run drift and Earth rate are not); its tilt error grows linearly with time since launch.
        """
        level = self.phase.level
        if level is None:
            return None
        sigma0 = level.roll_sigma_rad
        if self.phase.launch_time_s is None:
            return sigma0
        return math.hypot(sigma0, self.gyro_bias_sigma_rad_s * (time_s - self.phase.launch_time_s))

    def _solution(self, s: ImuSample) -> NavSolution:
        q_ns = self._q_nav_from_sensor()
        rates_body = dcm_from_quat(self.q_body_from_sensor) @ (s.gyro_rad_s - self.gyro_bias_rad_s)
        if q_ns is None:
            return NavSolution(s.time_fc_s, s.time_rx_s, self.phase.phase, None, None, None, rates_body)
        q_nb = quat_mul(q_ns, self.q_sensor_from_body)
        roll, pitch, _ = euler_from_quat(q_nb)
        sigma = self._tilt_sigma_rad(s.time_fc_s)
        return NavSolution(s.time_fc_s, s.time_rx_s, self.phase.phase, q_nb, roll, pitch, rates_body,
                           roll_sigma_rad=sigma, pitch_sigma_rad=sigma)
