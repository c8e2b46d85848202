"""The simulation engine shared by the offline API and the live autopilot: a truth flight, the
derived kinematic truth and the sensor suite, advanced chunk by chunk on one fixed clock."""
from __future__ import annotations

import numpy as np

from sim.scenario import load_scenario
from sim.sensors import SensorSuite
from sim.trajectory import Flight
from sim.truth import TruthDeriver


class Engine:
    """``chunk(n)`` -> dict of arrays for the next n samples (states, truth, continuous sensors)."""

    def __init__(self, scenario, seed: int = 0, imu_grade: str = "consumer", rate_hz: float = 200.0,
                 overrides: dict | None = None):
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
        if not (isinstance(rate_hz, (int, float)) and 10.0 <= rate_hz <= 4000.0):
            raise ValueError(f"imu_rate_hz must be in [10, 4000], got {rate_hz!r}")
        self.sc = load_scenario(scenario, overrides)
        self.seed = int(seed)
        self.imu_grade = imu_grade
        self.rate_hz = float(rate_hz)
        self.dt = 1.0 / self.rate_hz
        ss = np.random.SeedSequence(self.seed)
        s_traj, s_sens = ss.spawn(2)
        self.flight = Flight(self.sc, self.dt, np.random.default_rng(s_traj))
        self.deriver = TruthDeriver()
        self.sensors = SensorSuite(self.sc, imu_grade, self.dt, s_sens)

    @property
    def time_s(self) -> float:
        return self.flight.t

    def chunk(self, n: int) -> dict:
        st = self.flight.run(n)
        tr = self.deriver(st)
        ms = self.sensors.measure(st, tr)
        return {**st, **tr, **ms}

    def site(self) -> dict:
        S, L, sc = self.sc["site"], self.sc["launcher"], self.sc
        return {
            "lat_deg": S["lat_deg"], "lon_deg": S["lon_deg"], "alt_m": S["alt_m"],
            "decimal_year": sc["scenario"]["decimal_year"],
            "launcher_type": L["type"],
            "launcher_azimuth_deg": L["azimuth_deg"] % 360.0,
            "launcher_elevation_deg": L["elevation_deg"],
            "C_body_from_sensor": self.sensors.C_body_from_sensor.copy(),
            "personality": sc["autopilot"]["personality"],
            "imu_grade": self.imu_grade,
        }

