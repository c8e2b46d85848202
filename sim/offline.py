"""Offline API: a whole simulated flight as numpy arrays, exactly as the MAVLink stream would
carry the sensors after decoding to SI (all configured errors, RAW_IMU quantisation or HIGHRES_IMU
float32), plus the truth for scoring and the site an operator legitimately knows.

    from sim.offline import simulate
    run = simulate("inclined_rail", seed=0, imu_grade="consumer", imu_rate_hz=200.0,
                   duration_s=None, overrides=None)

Sensor arrays are in the SENSOR frame (IMU axes). A sensor dropout (faults.sensor_dropouts) shows
as NaN rows. Link faults (drops, corruption, reboot, outages, NaN fields) only apply live.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim import wire
from sim.engine import Engine
from sim.frames import euler_from_q
from sim.trajectory import PHASES

CHUNK_S = 20.0


@dataclass
class SimTruth:
    """Truth at the IMU sample times (the gyro/accel entries are averages over the preceding
    sample interval, as the IMU samples are)."""
    time_s: np.ndarray
    q_nav_from_body: np.ndarray       # (N, 4)
    euler_rad: np.ndarray             # (N, 3) [roll, pitch, yaw], yaw in (-pi, pi]
    q_nav_from_sensor: np.ndarray     # (N, 4)
    omega_body_rad_s: np.ndarray      # (N, 3) inertial rate in body axes (what an ideal gyro reads)
    omega_nb_body_rad_s: np.ndarray   # (N, 3) body rate relative to NED (Earth + transport rate removed)
    f_body_m_s2: np.ndarray           # (N, 3) specific force in body axes (ideal accelerometer)
    lat_rad: np.ndarray
    lon_rad: np.ndarray
    alt_m: np.ndarray
    vel_ned_m_s: np.ndarray           # (N, 3)
    airspeed_m_s: np.ndarray          # true airspeed |v - wind|
    field_ned_gauss: np.ndarray       # (N, 3) total field at the vehicle (sim.earth + site + anomalies)
    main_field_ned_gauss: np.ndarray  # (N, 3) IGRF-14 main field only (not the estimators' WMM)
    gravity_m_s2: np.ndarray          # (N,) normal gravity magnitude
    launch_time_s: float | None
    phase: np.ndarray                 # (N,) str: rest, boost, ground_roll, climb, level, turn, ...
    gyro_bias_end_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias_end_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class SimRun:
    time_s: np.ndarray                # (N,) FC clock, s (time_usec / 1e6), 0 at sim start
    gyro_rad_s: np.ndarray            # (N, 3) sensor frame
    accel_m_s2: np.ndarray            # (N, 3) sensor frame, at rest level ~ [0, 0, -g]
    mag_gauss: np.ndarray             # (N, 3) sensor frame
    baro_time_s: np.ndarray           # (M,)
    press_abs_pa: np.ndarray
    press_diff_pa: np.ndarray
    temperature_k: np.ndarray
    fc_time_s: np.ndarray             # (K,)
    fc_euler_rad: np.ndarray          # (K, 3) the FC's ATTITUDE [roll, pitch, yaw]
    gnss_lost_time_s: float | None
    truth: SimTruth
    site: dict
    scenario: dict
    seed: int
    imu_grade: str


def simulate(scenario="inclined_rail", seed: int = 0, imu_grade: str = "consumer", imu_rate_hz: float = 200.0,
             duration_s: float | None = None, overrides: dict | None = None) -> SimRun:
    """Run one flight. ``scenario``: a name in sim/scenarios/, a TOML path, or a dict;
    ``overrides``: nested dict deep-merged over it (same keys); ``duration_s`` defaults to
    scenario.duration_s. Deterministic in (scenario, overrides, seed, imu_grade, imu_rate_hz)."""
    eng = Engine(scenario, seed=seed, imu_grade=imu_grade, rate_hz=imu_rate_hz, overrides=overrides)
    dur = eng.sc["scenario"]["duration_s"] if duration_s is None else duration_s
    if isinstance(dur, bool) or not isinstance(dur, (int, float)) or not (0.0 < dur <= 86400.0):
        raise ValueError(f"duration_s must be in (0, 86400], got {duration_s!r}")
    n_total = int(round(dur * eng.rate_hz))
    step = max(1, int(CHUNK_S * eng.rate_hz))
    parts = []
    done = 0
    while done < n_total:
        k = min(step, n_total - done)
        parts.append(eng.chunk(k))
        done += k
    keys = [k for k, v in parts[0].items() if isinstance(v, np.ndarray)]
    d = {k: np.concatenate([p[k] for p in parts]) for k in keys}
    personality = eng.sc["autopilot"]["personality"]
    t_us = np.rint(d["time_s"] * 1e6)
    time_fc = t_us / 1e6
    gyro, accel, mag = wire.imu_as_decoded(personality, d["gyro_rad_s"], d["accel_m_s2"], d["mag_gauss"])
    k_baro = max(1, int(round(eng.rate_hz / eng.sc["baro"]["rate_hz"])))
    k_fc = max(1, int(round(eng.rate_hz / eng.sc["fc"]["rate_hz"])))
    pa, pd, tk = wire.pressure_as_decoded(d["press_abs_pa"][::k_baro], d["press_diff_pa"][::k_baro],
                                          d["temperature_k"][::k_baro])
    fc_eul = wire.f32(d["fc_euler_rad"][::k_fc])
    truth = SimTruth(
        time_s=d["time_s"], q_nav_from_body=d["q_nav_from_body"], euler_rad=euler_from_q(d["q_nav_from_body"]),
        q_nav_from_sensor=d["q_nav_from_sensor"], omega_body_rad_s=d["omega_body_rad_s"],
        omega_nb_body_rad_s=d["omega_nb_body_rad_s"], f_body_m_s2=d["f_body_m_s2"], lat_rad=d["lat_rad"],
        lon_rad=d["lon_rad"], alt_m=d["alt_m"], vel_ned_m_s=d["vel_ned_m_s"], airspeed_m_s=d["airspeed_m_s"],
        field_ned_gauss=d["field_ned_gauss"], main_field_ned_gauss=d["main_field_ned_gauss"], gravity_m_s2=d["gravity_m_s2"],
        launch_time_s=eng.flight.launch_time_s, phase=np.array(PHASES, dtype=object)[d["phase"]].astype(str),
        gyro_bias_end_rad_s=eng.sensors.gyro.bias_now(), accel_bias_end_m_s2=eng.sensors.accel.bias_now())
    return SimRun(time_s=time_fc, gyro_rad_s=gyro, accel_m_s2=accel, mag_gauss=mag,
                  baro_time_s=time_fc[::k_baro], press_abs_pa=pa, press_diff_pa=pd, temperature_k=tk,
                  fc_time_s=time_fc[::k_fc], fc_euler_rad=fc_eul, gnss_lost_time_s=eng.sc["gnss"]["lost_at_s"],
                  truth=truth, site=eng.site(), scenario=eng.sc, seed=int(seed), imu_grade=imu_grade)

