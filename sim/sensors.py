"""Sensor models: IMU (gyro, accelerometer), magnetometer, barometer, differential pressure, and
the flight controller's own attitude estimate. All measured in the SENSOR frame (IMU axes).

IMU error model per triad (sensor frame, x = C_sensor_from_body x_body):
    y = clip( (I + diag(s) + M) x + b0 + b_rw(t) + n ,  +-range )
  s: scale-factor errors, M: cross-axis misalignment (off-diagonal), b0: turn-on bias,
  b_rw: in-run bias random walk (sigma_rw * sqrt(dt) per step), n: white noise with density N
  (sample sigma = N / sqrt(dt)). Quantisation is the link's (sim.wire).
Magnetometer: m = W (C_sensor_from_nav B_nav) + h + n, B_nav = sim.earth's field (IGRF + model error
  + crustal field, not the estimators' WMM) + launch-site distortion
  (B_site exp(-d/d0), d = distance from the launcher) + anomalies (B_a exp(-(d_a/r_a)^2));
  W soft iron (3x3), h hard iron (gauss), both in the sensor frame. ``mag.disturbances`` add, over
  [start_s, end_s): a magnet nearby (``field_ned_gauss``, a constant NED field added to B_nav: it
  stays put while the body turns) or a magnet attached (``hard_iron_gauss``, added to h).
Barometer: p = p_atm(h) + bias + n; T = T_atm(h) + offset + n (sim.earth.Atmosphere, not ISA).
Differential pressure: q = 1/2 rho_atm(h) max(u, 0)^2 + offset + n, u = air-relative velocity along
  the body x axis.
"""
from __future__ import annotations

import math

import numpy as np

from sim import earth
from sim.frames import dcm_from_euler_deg, dcm_from_q, euler_from_q, q_from_dcm, qmul

DEG = math.pi / 180.0
G0_M_S2 = 9.80665

#: The two shipped IMU grades. Units in the key names; densities per sqrt(Hz), walks per sqrt(s).
GRADES: dict[str, dict[str, float]] = {
    "consumer": {  # MEMS of a hobby/commercial FC (ICM-42688 / BMI088 class)
        "gyro_noise_density_rad_s_rthz": 0.005 * DEG,
        "gyro_turn_on_bias_sigma_rad_s": 0.2 * DEG,
        "gyro_bias_walk_rad_s_rts": 2e-5,
        "gyro_scale_sigma": 3e-3,
        "gyro_misalign_sigma_rad": 3e-3,
        "gyro_range_rad_s": 2000.0 * DEG,
        "accel_noise_density_m_s2_rthz": 150e-6 * G0_M_S2,
        "accel_turn_on_bias_sigma_m_s2": 0.1,
        "accel_bias_walk_m_s2_rts": 1e-4,
        "accel_scale_sigma": 3e-3,
        "accel_misalign_sigma_rad": 3e-3,
        "accel_range_m_s2": 16.0 * G0_M_S2,
        "mag_noise_gauss": 0.003,
    },
    "tactical": {  # tactical-grade MEMS (ADIS1650x / STIM300 class)
        "gyro_noise_density_rad_s_rthz": 0.15 * DEG / 60.0,   # 0.15 deg/sqrt(h)
        "gyro_turn_on_bias_sigma_rad_s": 1.0 * DEG / 3600.0,  # 1 deg/h
        "gyro_bias_walk_rad_s_rts": 1e-7,
        "gyro_scale_sigma": 1e-4,
        "gyro_misalign_sigma_rad": 1e-4,
        "gyro_range_rad_s": 1000.0 * DEG,
        "accel_noise_density_m_s2_rthz": 30e-6 * G0_M_S2,
        "accel_turn_on_bias_sigma_m_s2": 1e-3 * G0_M_S2,
        "accel_bias_walk_m_s2_rts": 1e-5,
        "accel_scale_sigma": 3e-4,
        "accel_misalign_sigma_rad": 1e-4,
        "accel_range_m_s2": 40.0 * G0_M_S2,
        "mag_noise_gauss": 0.0005,
    },
}

#: [imu] keys besides the grade's: mount and optional explicit error values replacing the draws
IMU_EXTRA_KEYS = ("mount_euler_deg", "gyro_bias_rad_s", "accel_bias_m_s2", "gyro_scale", "accel_scale",
                  "gyro_misalignment", "accel_misalignment")


def imu_params(grade: str, imu_section: dict) -> dict:
    """The grade's table updated by the scenario's [imu] keys (validated)."""
    if grade not in GRADES:
        raise ValueError(f"imu_grade must be one of {sorted(GRADES)}, got {grade!r}")
    p = dict(GRADES[grade])
    for k, v in imu_section.items():
        if k not in p and k not in IMU_EXTRA_KEYS and k != "grade":
            raise ValueError(f"unknown key imu.{k}; known: {sorted(p) + list(IMU_EXTRA_KEYS)}")
        if k in p and (isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0 or not math.isfinite(v)):
            raise ValueError(f"imu.{k} must be a finite number >= 0, got {v!r}")
        p[k] = v
    return p


class Triad:
    """One inertial triad's errors (gyro or accelerometer), with chunk-continuous state."""

    def __init__(self, p: dict, kind: str, rng_const: np.random.Generator, rng_noise: np.random.Generator,
                 rng_walk: np.random.Generator, dt_s: float):
        self.kind, self.dt = kind, dt_s
        self.rng_noise, self.rng_walk = rng_noise, rng_walk
        unit = "rad_s" if kind == "gyro" else "m_s2"
        self.noise_sigma = p[f"{kind}_noise_density_{unit}_rthz"] / math.sqrt(dt_s)
        self.walk_sigma = p[f"{kind}_bias_walk_{unit}_rts"] * math.sqrt(dt_s)
        self.range = p[f"{kind}_range_{unit}"]
        draws_bias = rng_const.standard_normal(3) * p[f"{kind}_turn_on_bias_sigma_{unit}"]
        draws_scale = rng_const.standard_normal(3) * p[f"{kind}_scale_sigma"]
        draws_mis = rng_const.standard_normal(6) * p[f"{kind}_misalign_sigma_rad"]
        bias_key = "gyro_bias_rad_s" if kind == "gyro" else "accel_bias_m_s2"
        self.bias0 = np.asarray(p.get(bias_key, draws_bias), float)
        scale = np.asarray(p.get(f"{kind}_scale", draws_scale), float)
        if f"{kind}_misalignment" in p:
            M = np.asarray(p[f"{kind}_misalignment"], float)
        else:
            M = np.zeros((3, 3))
            M[[0, 0, 1, 1, 2, 2], [1, 2, 0, 2, 0, 1]] = draws_mis
        if self.bias0.shape != (3,) or scale.shape != (3,) or M.shape != (3, 3):
            raise ValueError(f"imu.{bias_key}/{kind}_scale must have 3 entries, {kind}_misalignment 3x3")
        self.T = np.eye(3) + np.diag(scale) + M
        self.walk = np.zeros(3)

    def measure(self, x_sensor: np.ndarray) -> np.ndarray:
        n = len(x_sensor)
        walk = self.walk + np.cumsum(self.rng_walk.standard_normal((n, 3)) * self.walk_sigma, axis=0)
        if n:
            self.walk = walk[-1].copy()
        y = x_sensor @ self.T.T + self.bias0 + walk + self.rng_noise.standard_normal((n, 3)) * self.noise_sigma
        return np.clip(y, -self.range, self.range)

    def bias_now(self) -> np.ndarray:
        return self.bias0 + self.walk


class GaussMarkovGrid:
    """Unit-variance first-order Gauss-Markov series on a fixed global grid (t = i * step_s),
    linearly interpolated; extending it chunk by chunk gives the same values as one long call."""

    def __init__(self, rng: np.random.Generator, tau_s: float, n_series: int, step_s: float = 0.1):
        self.rng, self.n, self.step = rng, n_series, step_s
        self.a = math.exp(-step_s / tau_s) if tau_s > 0 else 0.0
        self.b = math.sqrt(1.0 - self.a * self.a)
        self.i0 = 0
        self.vals = rng.standard_normal((1, n_series))  # value at grid index i0

    def at(self, t: np.ndarray) -> np.ndarray:
        i_need = int(math.floor(t[-1] / self.step)) + 1
        i_last = self.i0 + len(self.vals) - 1
        if i_need > i_last:
            m = i_need - i_last
            noise = self.rng.standard_normal((m, self.n))
            new = np.empty((m, self.n))
            x = self.vals[-1]
            for j in range(m):
                x = self.a * x + self.b * noise[j]
                new[j] = x
            self.vals = np.vstack([self.vals, new])
        tg = (self.i0 + np.arange(len(self.vals))) * self.step
        out = np.stack([np.interp(t, tg, self.vals[:, i]) for i in range(self.n)], -1)
        # keep only what the next chunk can still need
        keep_from = max(0, int(math.floor(t[-1] / self.step)) - self.i0)
        self.vals = self.vals[keep_from:]
        self.i0 += keep_from
        return out


class Vibration:
    """Motor vibration added to the true rate and specific force (sensor axes), from
    ``launcher.spinup_s`` before ``launcher.rest_s`` on, ramped in over 1 s (the spin-up):

        x_i(t) = s(t) sqrt(2) rms sin(phi(t) + c_i) + broadband,  phi(t) = 2 pi (f0 t - df T/(2 pi) cos(2 pi t / T))

    (the blade-pass frequency f0 wandering by +-df with period T = 7 s: a closed form, so chunks
    join exactly), phases c_i fixed per axis and sensor. Sampled at the sample times as is: a
    blade-pass above the Nyquist frequency aliases, as an FC's decimated stream does."""

    PERIOD_S = 7.0
    RAMP_S = 1.0

    def __init__(self, scenario: dict, rng: np.random.Generator):
        v, L = scenario["vibration"], scenario["launcher"]
        self.v = v
        self.on = bool(v["accel_rms_m_s2"] or v["gyro_rms_rad_s"] or v["broadband_accel_rms_m_s2"])
        self.t_on = L["rest_s"] - L["spinup_s"] if L["spinup_s"] > 0 else math.inf
        self.rng = rng
        self.c_accel, self.c_gyro = rng.uniform(0, 2 * math.pi, 3), rng.uniform(0, 2 * math.pi, 3)

    def add(self, t: np.ndarray, w_s: np.ndarray, f_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self.on or len(t) == 0 or t[-1] < self.t_on:
            return w_s, f_s
        v, T = self.v, self.PERIOD_S
        s = np.clip((t - self.t_on) / self.RAMP_S, 0.0, 1.0)[:, None]
        phi = 2 * math.pi * (v["freq_hz"] * t - v["freq_wander_hz"] * T / (2 * math.pi) * np.cos(2 * math.pi * t / T))
        f = f_s + s * (math.sqrt(2) * v["accel_rms_m_s2"] * np.sin(phi[:, None] + self.c_accel)
                       + v["broadband_accel_rms_m_s2"] * self.rng.standard_normal((len(t), 3)))
        w = w_s + s * math.sqrt(2) * v["gyro_rms_rad_s"] * np.sin(phi[:, None] + self.c_gyro)
        return w, f


class SensorSuite:
    """All sensors of one vehicle; ``measure(truth_chunk)`` is chunk-continuous and deterministic."""

    def __init__(self, scenario: dict, imu_grade: str, dt_s: float, seed_seq: np.random.SeedSequence):
        rng = [np.random.default_rng(s) for s in seed_seq.spawn(12)]
        self.sc = scenario
        self.dt = dt_s
        self.p = imu_params(imu_grade, scenario["imu"])
        self.C_body_from_sensor = dcm_from_euler_deg(*scenario["imu"]["mount_euler_deg"])
        self.q_body_from_sensor = q_from_dcm(self.C_body_from_sensor)
        self.gyro = Triad(self.p, "gyro", rng[0], rng[1], rng[2], dt_s)
        self.accel = Triad(self.p, "accel", rng[3], rng[4], rng[5], dt_s)
        self.rng_mag, self.rng_baro, self.rng_air, self.rng_fc = rng[6], rng[7], rng[8], rng[9]
        self.rng_temp = rng[10]
        self.earth = earth.SimEarth(scenario, rng[11])
        M = scenario["mag"]
        self.W = np.asarray(M["soft_iron"], float)
        self.hard_iron = np.asarray(M["hard_iron_gauss"], float)
        self.mag_sigma = float(self.p["mag_noise_gauss"])
        self.site_field = np.asarray(M["site_distortion_ned_gauss"], float)
        self.site_fade = float(M["site_distortion_fade_m"])
        self.anomalies = M["anomalies"]
        self.disturbances = M.get("disturbances", [])
        self.year = scenario["scenario"]["decimal_year"]
        S = scenario["site"]
        self.lat0, self.lon0, self.h0 = math.radians(S["lat_deg"]), math.radians(S["lon_deg"]), S["alt_m"]
        F = scenario["fc"]
        self.fc_p = F
        self.gnss_lost_s = scenario["gnss"]["lost_at_s"]
        self.fc_gm = GaussMarkovGrid(self.rng_fc, F["error_tau_s"], 3)
        self.fc_drift_sign = float(self.rng_fc.choice([-1.0, 1.0]))
        self.dropouts = scenario["faults"]["sensor_dropouts"]
        self.vibration = Vibration(scenario, np.random.default_rng(seed_seq.spawn(1)[0]))

    # -- magnetic field ------------------------------------------------------------------
    def field_ned_gauss(self, st: dict) -> tuple[np.ndarray, np.ndarray]:
        """(IGRF main field, total field incl. model error, crustal field, site distortion and
        anomalies), NED gauss, (n, 3)."""
        main, total = self.earth.field_ned_gauss(st["lat_rad"], st["lon_rad"], st["alt_m"])
        if np.any(self.site_field) or self.anomalies:
            ned = earth.ned_offset_m(self.lat0, self.lon0, self.h0, st["lat_rad"], st["lon_rad"], st["alt_m"])
            if np.any(self.site_field):
                d = np.linalg.norm(ned, axis=1)
                total += np.exp(-d / self.site_fade)[:, None] * self.site_field
            for a in self.anomalies:
                c = np.array([a["north_m"], a["east_m"], a.get("down_m", 0.0)])
                d2 = np.sum((ned - c) ** 2, axis=1) / float(a["radius_m"]) ** 2
                total += np.exp(-d2)[:, None] * np.asarray(a["field_ned_gauss"], float)
        return main, total

    def _dropout_mask(self, sensor: str, t: np.ndarray) -> np.ndarray:
        m = np.zeros(len(t), bool)
        for d in self.dropouts:
            if d["sensor"] == sensor:
                m |= (t >= d["start_s"]) & (t < d["end_s"])
        return m

    # -- one chunk -----------------------------------------------------------------------
    def measure(self, st: dict, tr: dict) -> dict:
        """Continuous-valued measurements (before the link's quantisation), sensor frame, SI."""
        q_ns = qmul(tr["q_nav_from_body"], self.q_body_from_sensor)
        C_ns = dcm_from_q(q_ns)
        C_sb = self.C_body_from_sensor.T
        w_s = tr["omega_body_rad_s"] @ C_sb.T
        f_s = tr["f_body_m_s2"] @ C_sb.T
        w_s, f_s = self.vibration.add(st["time_s"], w_s, f_s)
        main, total = self.field_ned_gauss(st)
        t = st["time_s"]
        hard = self.hard_iron
        if self.disturbances:
            total, hard = total.copy(), np.broadcast_to(hard, (len(t), 3)).copy()
            for d in self.disturbances:
                on = ((t >= d["start_s"]) & (t < d.get("end_s", math.inf)))[:, None]
                if "field_ned_gauss" in d:
                    total += on * np.asarray(d["field_ned_gauss"], float)
                else:
                    hard += on * np.asarray(d["hard_iron_gauss"], float)
        b_s = np.einsum("nji,nj->ni", C_ns, total)
        n = len(w_s)
        gyro = self.gyro.measure(w_s)
        accel = self.accel.measure(f_s)
        mag = b_s @ self.W.T + hard + self.rng_mag.standard_normal((n, 3)) * self.mag_sigma
        t = st["time_s"]
        B = self.sc["baro"]
        atm = self.earth.atmosphere
        press = atm.pressure_pa(st["alt_m"]) + B["bias_pa"] + self.rng_baro.standard_normal(n) * B["noise_pa"]
        temp = atm.temperature_k(st["alt_m"]) + B["temperature_offset_k"] + \
            self.rng_temp.standard_normal(n) * B["temperature_noise_k"]
        A = self.sc["airspeed"]
        u = np.maximum(tr["air_body_m_s"][:, 0], 0.0)
        diff = 0.5 * atm.density_kg_m3(st["alt_m"]) * u * u + A["offset_pa"] + \
            self.rng_air.standard_normal(n) * A["noise_pa"]
        for arr, name in ((gyro, "imu"), (accel, "imu"), (mag, "imu"), (mag, "mag")):
            arr[self._dropout_mask(name, t)] = np.nan
        press[self._dropout_mask("baro", t)] = np.nan
        temp[self._dropout_mask("baro", t)] = np.nan
        diff[self._dropout_mask("airspeed", t)] = np.nan
        return {"gyro_rad_s": gyro, "accel_m_s2": accel, "mag_gauss": mag, "press_abs_pa": press,
                "temperature_k": temp, "press_diff_pa": diff, "q_nav_from_sensor": q_ns,
                "field_ned_gauss": total, "main_field_ned_gauss": main, "fc_euler_rad": self.fc_attitude(t, tr)}

    def fc_attitude(self, t: np.ndarray, tr: dict) -> np.ndarray:
        """The FC's own estimate: truth Euler + Gauss-Markov errors; after GNSS loss the tilt error
        grows to degraded_tilt_error_deg and the yaw drifts at degraded_yaw_drift_deg_s."""
        eul = euler_from_q(tr["q_nav_from_body"])
        if len(t) == 0:
            return eul
        F = self.fc_p
        e = self.fc_gm.at(t)
        sig_rp = np.full(len(t), math.radians(F["roll_pitch_error_deg"]))
        sig_y = np.full(len(t), math.radians(F["yaw_error_deg"]))
        drift = np.zeros(len(t))
        if self.gnss_lost_s is not None:
            since = np.maximum(t - self.gnss_lost_s, 0.0)
            ramp = np.minimum(since / 30.0, 1.0)
            sig_rp = sig_rp + ramp * (math.radians(F["degraded_tilt_error_deg"]) - sig_rp)
            drift = self.fc_drift_sign * math.radians(F["degraded_yaw_drift_deg_s"]) * since
        out = eul.copy()
        out[:, 0] += sig_rp * e[:, 0]
        out[:, 1] = np.clip(out[:, 1] + sig_rp * e[:, 1], -math.pi / 2, math.pi / 2)
        out[:, 2] = np.angle(np.exp(1j * (out[:, 2] + sig_y * e[:, 2] + drift)))
        return out
