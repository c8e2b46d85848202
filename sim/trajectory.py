"""Truth trajectory: a kinematic 6-DOF flight stepped on a fixed clock.

State (scalars, stepped in plain Python for speed): geodetic position (lat, lon, h), the
air-relative flight-path speed V, heading psi (yaw of the velocity frame, unwrapped), flight
path angle gamma, bank phi, angle of attack alpha, and the wind (mean + Gauss-Markov gusts).

Attitude: q_nav_from_body = qz(psi) qy(gamma) qx(phi) qy(alpha)
  (velocity frame turned by the bank, then the body pitched up by alpha about its y axis).
Coordinated turn: psi_dot = g tan(phi) / V, so bank = atan(V psi_dot / g).
Ground velocity: v_ned = V [cos g cos psi, cos g sin psi, -sin g] + wind felt by the airframe
(the mean wind plus gusts lagged by ``gust_response_tau_s``); the air-relative velocity that the
pitot sees is v_ned - (mean wind + instantaneous gust).
Position: lat' = vN/(R_M+h), lon' = vE/((R_N+h) cos lat), h' = -vD.

The sensors-side truth (angular rate, specific force) is derived from the sampled states in
``sim.truth`` by differencing, so it is consistent with the attitude and velocity histories.

Take-offs besides the rail/tube boost and the runway roll (``launcher.type``):
- ``hand``: on the ground until ``pickup_s`` before the throw; picked up (lifted 0.6 m in 1 s, peak 3.8 m/s^2, while
  pitched to ``elevation_deg``), held with a sway of the hand (pitch 1 deg at 0.7 Hz + 0.15 deg
  tremor at 8 Hz, yaw 1.5 deg at 0.4 Hz; all times ``hand_sway_scale``), then thrown: ``boost_accel_m_s2`` for ``boost_time_s``
  along the flight axis. A vertical velocity uses gamma = +-90 deg with alpha = pitch - gamma, so
  the body attitude qy(gamma) qy(alpha) = qy(pitch) is independent of where the vehicle moves.
- ``multicopter`` / ``vtol``: a vertical lift-off at ``rest_s`` (the same gamma/alpha pairing with
  a level body): ``liftoff_accel_m_s2`` up to ``climb_rate_m_s``, decelerating to a hover at
  ``hover_alt_m``, a hover of ``hover_s``, then the legs in forward flight from zero airspeed
  (vtol: the transition; multicopter: the same forward-flight kinematics, an approximation).
The motors (vibration, sim.sensors) start ``spinup_s`` before ``rest_s``.
- ``rig``: an IMU moved by hand or on a rig (or a hovering vehicle's attitude alone): the position stays
  at the site (V = 0) and from ``rest_s`` the attitude follows ``[[motion.segments]]`` (below).

Motion segments (``rig``): the attitude is the ZYX Euler triple (roll phi, pitch gamma, yaw psi; alpha = 0,
so q = qz(psi) qy(gamma) qx(phi), valid through pitch +-90 deg because the angles are smooth in time, not
derived from an attitude). Segment i changes them by ``by_deg`` = [droll, dpitch, dyaw] over ``duration_s``
with the smooth step s(u) = (1 - cos(pi u)) / 2, u = time in segment / duration (zero rate at both ends;
peak Euler rate = pi |d| / (2 duration)); ``by_deg`` = [0, 0, 0] is a still pause. An optional
``move_m`` = [dn, de, dd] translates the IMU with the same step (peak acceleration pi^2 |d| / (2 T^2)). After the last segment
the IMU holds still. The body rates the gyro sees come from differencing q (sim.truth), as for flights.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.earth import gravity_m_s2, radii_m

PHASES = ("rest", "boost", "ground_roll", "climb", "descend", "level", "turn", "figure8", "loiter",
          "goto", "rtl", "hand", "liftoff", "hover", "rig")
ON_GROUND_PHASES = ("rest", "boost", "ground_roll", "hand", "rig")
HAND_LIFT_S, HAND_LIFT_M = 1.0, 0.6
"""The hand launch's pick-up: lifted this high (m) in this long (s)."""
PHASE_CODE = {p: i for i, p in enumerate(PHASES)}
EARTH_MEAN_RADIUS_M = 6371008.8
GUIDANCE_PERIOD_S = 0.02
POLE_GUARD_DEG = 89.99


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def gc_bearing_distance(lat1, lon1, lat2, lon2) -> tuple[float, float]:
    """Initial great-circle bearing (rad, from local north at point 1) and distance (m)."""
    dlon = lon2 - lon1
    y = math.sin(dlon) * math.cos(lat2)
    x = math.cos(lat1) * math.sin(lat2) - math.sin(lat1) * math.cos(lat2) * math.cos(dlon)
    hav = math.sin((lat2 - lat1) / 2) ** 2 + math.cos(lat1) * math.cos(lat2) * math.sin(dlon / 2) ** 2
    return math.atan2(y, x), 2.0 * EARTH_MEAN_RADIUS_M * math.asin(min(1.0, math.sqrt(hav)))


def gc_destination(lat, lon, bearing, dist_m) -> tuple[float, float]:
    d = dist_m / EARTH_MEAN_RADIUS_M
    lat2 = math.asin(math.sin(lat) * math.cos(d) + math.cos(lat) * math.sin(d) * math.cos(bearing))
    lon2 = lon + math.atan2(math.sin(bearing) * math.sin(d) * math.cos(lat),
                            math.cos(d) - math.sin(lat) * math.sin(lat2))
    return lat2, lon2


@dataclass
class Leg:
    """One guidance leg (a parsed ``[[legs]]`` entry)."""
    kind: str
    phase: str
    p: dict
    started: bool = False
    t0: float = 0.0
    psi_target: float = 0.0
    alt_target: float = 0.0
    center: tuple[float, float] | None = None
    reached: bool = False


def expand_legs(legs: list[dict]) -> list[Leg]:
    out: list[Leg] = []
    for i, d in enumerate(legs):
        kind = d["type"]
        known = {"type", "alt_m", "rate_m_s", "heading_deg", "airspeed_m_s", "duration_s", "by_deg", "bank_deg",
                 "loops", "radius_m", "direction", "north_m", "east_m", "lat_deg", "lon_deg", "acceptance_m"}
        extra = set(d) - known
        if extra:
            raise ValueError(f"legs[{i}] ({kind}): unknown key(s) {sorted(extra)}")
        if kind in ("climb", "descend") and "alt_m" not in d:
            raise ValueError(f"legs[{i}] ({kind}) needs alt_m (height above the launch site, m)")
        if kind == "level" and "duration_s" not in d:
            raise ValueError(f"legs[{i}] (level) needs duration_s")
        if kind == "turn" and "by_deg" not in d and "heading_deg" not in d:
            raise ValueError(f"legs[{i}] (turn) needs by_deg (+ right) or heading_deg")
        if "bank_deg" in d and not (0.0 < d["bank_deg"] <= 60.0):
            raise ValueError(f"legs[{i}].bank_deg must be in (0, 60], got {d['bank_deg']}")
        if kind == "goto" and not (("north_m" in d and "east_m" in d) or ("lat_deg" in d and "lon_deg" in d)):
            raise ValueError(f"legs[{i}] (goto) needs north_m+east_m or lat_deg+lon_deg")
        if d.get("direction", "cw") not in ("cw", "ccw"):
            raise ValueError(f"legs[{i}].direction must be 'cw' or 'ccw', got {d['direction']!r}")
        if kind == "figure8":
            for _ in range(int(d.get("loops", 1))):
                out.append(Leg("turn", "figure8", {**d, "by_deg": 360.0}))
                out.append(Leg("turn", "figure8", {**d, "by_deg": -360.0}))
        else:
            out.append(Leg(kind, kind, dict(d)))
    return out


def _rig_table(segments: list[dict]) -> tuple[np.ndarray, ...]:
    """Motion segments as arrays: start (s after rest_s), duration (s), change and start angles
    ([roll, pitch, yaw] rad, the start from 0 = level, facing launcher.azimuth_deg, added later),
    and the translation of each (NED m)."""
    starts, durs, bys, base, moves = [], [], [], [], []
    t, ang = 0.0, np.zeros(3)
    for seg in segments:
        d = np.radians(np.asarray(seg["by_deg"], float))
        starts.append(t), durs.append(float(seg["duration_s"])), bys.append(d), base.append(ang.copy())
        moves.append(np.asarray(seg.get("move_m", [0.0, 0.0, 0.0]), float))
        t += float(seg["duration_s"])
        ang = ang + d
    if not segments:
        starts, durs, bys, base, moves = [0.0], [1.0], [np.zeros(3)], [np.zeros(3)], [np.zeros(3)]
    return np.array(starts), np.array(durs), np.array(bys), np.array(base), np.array(moves)


class Flight:
    """The truth vehicle. ``run(n)`` steps n samples of ``dt_s`` and returns the sampled states."""

    def __init__(self, scenario: dict, dt_s: float, rng: np.random.Generator):
        if not (0.0 < dt_s <= 0.1):
            raise ValueError(f"dt_s must be in (0, 0.1], got {dt_s}")
        self.sc = scenario
        self.dt = dt_s
        self.rng = rng
        L, F, W = scenario["launcher"], scenario["flight"], scenario["wind"]
        self.L, self.F = L, F
        self.lat0 = math.radians(scenario["site"]["lat_deg"])
        self.lon0 = math.radians(scenario["site"]["lon_deg"])
        self.h0 = scenario["site"]["alt_m"]
        self.lat, self.lon, self.h = self.lat0, self.lon0, self.h0
        self.t = 0.0
        self.k = 0
        self.V = 0.0
        self.psi = math.radians(L["azimuth_deg"])
        self.gamma = math.radians(L["elevation_deg"])
        self.phi = math.radians(L["roll_deg"])
        self.alpha = math.radians(L["ground_pitch_deg"]) if L["type"] == "runway" else 0.0
        if L["type"] in ("hand", "multicopter", "vtol", "rig"):  # on the ground, level
            self.gamma = self.phi = self.alpha = 0.0
        self.psi0 = self.psi
        self._t_phase = 0.0
        self.phase = "rest"
        self.launch_time_s: float | None = None
        self.boost_end_s: float | None = None
        self.wind_mean = np.array([W["north_m_s"], W["east_m_s"], W["down_m_s"]], float)
        self.gust = [0.0, 0.0, 0.0]
        self.gust_felt = [0.0, 0.0, 0.0]
        self.wind_gain = 0.0
        self.legs = expand_legs(scenario["legs"])
        self.leg_index = 0
        self.override: Leg | None = None
        self.cmd = (0.0, 0.0, F["cruise_airspeed_m_s"])
        self.g = float(gravity_m_s2(self.lat0, self.h0))
        self._next_guidance_t = 0.0
        self.vel = (0.0, 0.0, 0.0)
        self.air = (0.0, 0.0, 0.0)
        self._radii = radii_m(self.lat0)
        self._rig = _rig_table(scenario.get("motion", {}).get("segments", [])) if L["type"] == "rig" else None
        self._rig_vel = (0.0, 0.0, 0.0)

    # ---- commands from the autopilot side ------------------------------------------------
    def command_rtl(self) -> None:
        self.override = Leg("rtl", "rtl", {"lat_deg": math.degrees(self.lat0), "lon_deg": math.degrees(self.lon0)})

    def command_loiter(self, lat_rad: float | None = None, lon_rad: float | None = None,
                       alt_rel_m: float | None = None) -> None:
        p: dict = {"radius_m": self.F["loiter_radius_m"]}
        if lat_rad is not None and lon_rad is not None:
            p.update(lat_deg=math.degrees(lat_rad), lon_deg=math.degrees(lon_rad))
        if alt_rel_m is not None:
            p["alt_m"] = alt_rel_m
        self.override = Leg("loiter", "loiter", p)

    def command_reposition(self, lat_rad: float, lon_rad: float, alt_rel_m: float | None) -> None:
        p = {"lat_deg": math.degrees(lat_rad), "lon_deg": math.degrees(lon_rad)}
        if alt_rel_m is not None:
            p["alt_m"] = alt_rel_m
        self.override = Leg("goto", "goto", {**p, "then_loiter": True})

    def command_resume(self) -> None:
        self.override = None

    @property
    def airborne(self) -> bool:
        return self.phase not in ON_GROUND_PHASES

    # ---- guidance -------------------------------------------------------------------------
    def _rate_max(self, bank_rad: float) -> float:
        return self.g * math.tan(bank_rad) / max(self.V, 1.0)

    def _heading_hold(self, psi_t: float, bank_rad: float) -> float:
        rm = self._rate_max(bank_rad)
        return max(-rm, min(rm, self.F["heading_gain_1_s"] * _wrap_pi(psi_t - self.psi)))

    def _course_to(self, bearing: float, bank_rad: float, ff: float = 0.0) -> float:
        vn, ve, _ = self.vel
        course = math.atan2(ve, vn) if vn * vn + ve * ve > 1.0 else self.psi
        rm = self._rate_max(bank_rad)
        return max(-rm, min(rm, ff + self.F["heading_gain_1_s"] * 2.0 * _wrap_pi(bearing - course)))

    def _alt_hold(self, alt_t: float) -> float:
        F = self.F
        return max(-F["max_sink_m_s"], min(F["max_climb_m_s"], F["alt_gain_1_s"] * (alt_t - (self.h - self.h0))))

    def _leg_target_latlon(self, p: dict) -> tuple[float, float]:
        if "lat_deg" in p:
            return math.radians(p["lat_deg"]), math.radians(p["lon_deg"])
        if "north_m" not in p:  # rtl: home is the launcher
            return self.lat0, self.lon0
        n, e = p["north_m"], p["east_m"]
        return gc_destination(self.lat0, self.lon0, math.atan2(e, n), math.hypot(n, e))

    def _loiter_cmd(self, leg: Leg, bank_max: float) -> float:
        p = leg.p
        r = p.get("radius_m", self.F["loiter_radius_m"])
        sgn = 1.0 if p.get("direction", "cw") == "cw" else -1.0
        if leg.center is None:
            if "lat_deg" in p:
                leg.center = (math.radians(p["lat_deg"]), math.radians(p["lon_deg"]))
            else:
                leg.center = gc_destination(self.lat, self.lon, self.psi + sgn * math.pi / 2, r)
        brg_vc, d = gc_bearing_distance(self.lat, self.lon, *leg.center)
        vn, ve, _ = self.vel
        vg = max(1.0, math.hypot(vn, ve))
        # desired course: tangent, turned inward when outside the circle (vector field)
        course_d = brg_vc + math.pi + sgn * (math.pi / 2 + math.atan(2.0 * (d - r) / r))
        return self._course_to(course_d, bank_max, ff=sgn * vg / r if d < 3 * r else 0.0)

    def _guidance(self) -> None:
        F = self.F
        bank_max = math.radians(F["max_bank_deg"])
        if self.override is not None:
            leg = self.override
        elif self.leg_index < len(self.legs):
            leg = self.legs[self.leg_index]
        else:
            leg = Leg("loiter", "loiter", {})
            self.legs.append(leg)
            self.leg_index = len(self.legs) - 1
        p = leg.p
        if not leg.started:
            leg.started, leg.t0 = True, self.t
            leg.alt_target = p.get("alt_m", self.h - self.h0)
            if leg.kind == "turn":
                if "by_deg" in p:
                    leg.psi_target = self.psi + math.radians(p["by_deg"])
                else:
                    leg.psi_target = self.psi + _wrap_pi(math.radians(p["heading_deg"]) - self.psi)
            else:
                leg.psi_target = math.radians(p["heading_deg"]) if "heading_deg" in p else self.psi
        bank = min(bank_max, math.radians(p.get("bank_deg", F["max_bank_deg"])))
        v_c = p.get("airspeed_m_s", F["cruise_airspeed_m_s"])
        psi_dot, climb, done = 0.0, self._alt_hold(leg.alt_target), False
        near_vertical = math.cos(self.gamma) < 0.5
        if leg.kind in ("climb", "descend"):
            err = leg.alt_target - (self.h - self.h0)
            rate = p.get("rate_m_s", F["max_climb_m_s"] if err > 0 else F["max_sink_m_s"])
            climb = math.copysign(min(abs(rate), abs(F["alt_gain_1_s"] * err) + 0.5), err)
            psi_dot = 0.0 if near_vertical else self._heading_hold(leg.psi_target, bank)
            done = abs(err) < 2.0
        elif leg.kind == "level":
            psi_dot = self._heading_hold(leg.psi_target, bank)
            done = self.t - leg.t0 >= p["duration_s"]
        elif leg.kind == "turn":
            rm = self._rate_max(bank)
            psi_dot = max(-rm, min(rm, F["heading_gain_1_s"] * (leg.psi_target - self.psi)))
            done = abs(leg.psi_target - self.psi) < math.radians(0.5)
        elif leg.kind == "loiter":
            psi_dot = self._loiter_cmd(leg, bank)
            done = "duration_s" in p and self.t - leg.t0 >= p["duration_s"]
        elif leg.kind in ("goto", "rtl"):
            if leg.reached:
                psi_dot = self._loiter_cmd(leg, bank)
            else:
                lat_t, lon_t = self._leg_target_latlon(p)
                brg, d = gc_bearing_distance(self.lat, self.lon, lat_t, lon_t)
                psi_dot = self._course_to(brg, bank)
                if d < p.get("acceptance_m", F["loiter_radius_m"]):
                    if leg.kind == "rtl" or p.get("then_loiter"):
                        leg.reached = True
                        leg.p = {**p, "lat_deg": math.degrees(lat_t), "lon_deg": math.degrees(lon_t)}
                    else:
                        done = True
        if near_vertical:
            psi_dot = 0.0
        self.phase = leg.phase
        self.cmd = (psi_dot, climb, v_c)
        if done and leg is not self.override:
            self.leg_index += 1

    # ---- take-offs besides the boost and the roll (module docstring) --------------------------
    def _set_vertical(self, v_up_m_s: float, pitch_rad: float) -> None:
        """Move vertically at v_up (m/s) with the body at pitch (rad), wings level."""
        self.gamma = math.pi / 2 if v_up_m_s >= 0.0 else -math.pi / 2
        self.V = abs(v_up_m_s)
        self.alpha = pitch_rad - self.gamma
        self.phi = 0.0

    def _hand_step(self, L: dict) -> None:
        """Picked up, held with the hand's sway, thrown at rest_s."""
        u = self.t + self.dt - self._t_phase  # state for the next sample
        elev = math.radians(L["elevation_deg"])
        if self.t + self.dt >= L["rest_s"] - 1e-9:  # the throw
            pitch = self.gamma + self.alpha
            self.gamma, self.V = elev, 0.0
            self.alpha = pitch - elev
            self.launch_time_s = self.t + self.dt
            self.phase, self.boost_end_s = "boost", self.t + self.dt + L["boost_time_s"]
            return
        if u < HAND_LIFT_S:  # raised cosine: lifted HAND_LIFT_M, pitched up smoothly
            x = u / HAND_LIFT_S
            v_up = HAND_LIFT_M / HAND_LIFT_S * (1.0 - math.cos(2.0 * math.pi * x))
            pitch = elev * (x - math.sin(2.0 * math.pi * x) / (2.0 * math.pi))
            self._set_vertical(v_up, pitch)
            return
        w = u - HAND_LIFT_S  # held: the hand's sway and tremor (they start from zero)
        k = L["hand_sway_scale"]
        pitch = elev + k * (math.radians(1.0) * math.sin(2 * math.pi * 0.7 * w)
                            + math.radians(0.15) * math.sin(2 * math.pi * 8.0 * w))
        self.psi = self.psi0 + k * math.radians(1.5) * math.sin(2 * math.pi * 0.4 * w)
        self._set_vertical(0.0, pitch)

    def _liftoff_step(self, L: dict) -> None:
        """Vertical lift-off: accelerate to the climb rate, brake into a hover at hover_alt_m."""
        a, vc = L["liftoff_accel_m_s2"], L["climb_rate_m_s"]
        to_go = L["hover_alt_m"] - (self.h - self.h0)
        v = self.V
        if v * v / (2.0 * a) >= to_go:  # braking distance reached: decelerate
            v = max(0.0, v - a * self.dt)
            if v == 0.0:
                self.phase, self._t_phase = "hover", self.t + self.dt
        else:
            v = min(vc, v + a * self.dt)
        self._set_vertical(v, 0.0)

    def _rig_step(self, L: dict) -> None:
        """The attitude of the next sample from the motion segments (module docstring)."""
        u = self.t + self.dt - L["rest_s"]
        starts, durs, bys, base, moves = self._rig
        i = int(np.searchsorted(starts, u, side="right")) - 1
        self._rig_vel = (0.0, 0.0, 0.0)
        if i < 0:
            ang = base[0]
        elif u >= starts[i] + durs[i]:
            ang = base[i] + bys[i]
        else:
            x = (u - starts[i]) / durs[i]
            ang = base[i] + bys[i] * (0.5 - 0.5 * math.cos(math.pi * x))
            # the translation's velocity: d/dt of move * (1 - cos(pi x)) / 2
            v = moves[i] * (0.5 * math.pi / durs[i] * math.sin(math.pi * x))
            self._rig_vel = (float(v[0]), float(v[1]), float(v[2]))
        self.phi, self.gamma, self.psi = float(ang[0]), float(ang[1]), self.psi0 + float(ang[2])
        self.alpha, self.V = 0.0, 0.0

    # ---- stepping --------------------------------------------------------------------------
    def run(self, n: int) -> dict[str, np.ndarray]:
        """Sample the state at the current time, then step; n times. Returns arrays of length n:
        time_s, lat_rad, lon_rad, alt_m, vel_ned_m_s (n,3), air_ned_m_s (n,3), psi, gamma, phi,
        alpha (rad), phase (int codes into PHASES)."""
        dt = self.dt
        F, L = self.F, self.L
        W = self.sc["wind"]
        out = np.empty((n, 16))
        phase_out = np.empty(n, dtype=np.int8)
        gust_sigma, gust_tau = W["gust_sigma_m_s"], W["gust_tau_s"]
        gust_noise = self.rng.standard_normal((n, 3)) * (gust_sigma * math.sqrt(2.0 * dt / gust_tau)) \
            if gust_sigma > 0 else np.zeros((n, 3))
        gust_a = dt / gust_tau
        resp_a = dt / F["gust_response_tau_s"]
        bank_tau, bank_rate = F["bank_tau_s"], math.radians(F["bank_rate_deg_s"])
        gam_tau, gam_rate = F["gamma_tau_s"], math.radians(F["gamma_rate_deg_s"])
        max_bank = math.radians(F["max_bank_deg"])
        alpha_trim = math.radians(F["alpha_deg"])
        v_cruise = F["cruise_airspeed_m_s"]
        wm = self.wind_mean
        for i in range(n):
            # ---- sample ----
            cg, sg = math.cos(self.gamma), math.sin(self.gamma)
            cp, sp = math.cos(self.psi), math.sin(self.psi)
            wg = self.wind_gain
            gf, gu = self.gust_felt, self.gust
            vn = self.V * cg * cp + wg * (wm[0] + gf[0])
            ve = self.V * cg * sp + wg * (wm[1] + gf[1])
            vd = -self.V * sg + wg * (wm[2] + gf[2])
            if self._rig is not None:  # the rig's translation (V = 0)
                vn, ve, vd = self._rig_vel
            self.vel = (vn, ve, vd)
            an, ae, ad = vn - wm[0] - gu[0], ve - wm[1] - gu[1], vd - wm[2] - gu[2]
            self.air = (an, ae, ad)
            out[i] = (self.t, self.lat, self.lon, self.h, vn, ve, vd, an, ae, ad,
                      self.psi, self.gamma, self.phi, self.alpha, 0.0, 0.0)
            phase_out[i] = PHASE_CODE[self.phase]
            # ---- step ----
            for j in range(3):
                gu[j] += -gu[j] * gust_a + gust_noise[i, j]
                gf[j] += (gu[j] - gf[j]) * resp_a
            ph = self.phase
            if ph == "rest":
                if L["type"] == "hand" and self.t + 1e-9 >= L["rest_s"] - L["pickup_s"]:
                    self.phase, self._t_phase = "hand", self.t
                elif L["type"] in ("multicopter", "vtol") and self.t + 1e-9 >= L["rest_s"]:
                    self.launch_time_s = self.t
                    self.phase = "liftoff"
                    self.gamma, self.alpha = math.pi / 2, -math.pi / 2  # moving up, body level
                elif L["type"] == "rig" and self.t + 1e-9 >= L["rest_s"]:
                    self.phase = "rig"
                    self._rig_step(L)
                elif L["type"] not in ("hand", "rig") and self.t + 1e-9 >= L["rest_s"]:
                    self.launch_time_s = self.t
                    self.phase = "ground_roll" if L["type"] == "runway" else "boost"
                    self.boost_end_s = self.t + L["boost_time_s"]
            elif ph == "hand":
                self._hand_step(L)
            elif ph == "rig":
                self._rig_step(L)
            elif ph == "liftoff":
                self._liftoff_step(L)
            elif ph == "hover":
                self.V = 0.0
                if self.t + 1e-9 >= self._t_phase + L["hover_s"]:  # forward flight from here
                    self.gamma = self.alpha = 0.0  # same (level) body attitude, V = 0
                    self._next_guidance_t = self.t + dt
                    self.phase = "climb"
            elif ph == "boost":
                self.V += L["boost_accel_m_s2"] * dt
                if self.t + dt >= self.boost_end_s - 1e-9:
                    self._next_guidance_t = self.t + dt
                    self.phase = "climb"
            elif ph == "ground_roll":
                self.V += L["takeoff_accel_m_s2"] * dt
                an_, ae_, ad_ = self.air
                if an_ * an_ + ae_ * ae_ + ad_ * ad_ >= L["rotate_airspeed_m_s"] ** 2:  # true airspeed
                    self._next_guidance_t = self.t + dt
                    self.phase = "climb"
            else:
                if self.t >= self._next_guidance_t - 1e-9:
                    self._guidance()
                    self._next_guidance_t += GUIDANCE_PERIOD_S
                psi_dot_c, climb_c, v_c = self.cmd
                V = max(self.V, 1.0)
                phi_c = max(-max_bank, min(max_bank, math.atan(V * psi_dot_c / self.g)))
                dphi = max(-bank_rate, min(bank_rate, (phi_c - self.phi) / bank_tau))
                gam_c = math.asin(max(-0.95, min(0.95, climb_c / V)))
                dgam = max(-gam_rate, min(gam_rate, (gam_c - self.gamma) / gam_tau))
                dv = max(-F["max_accel_m_s2"], min(F["max_accel_m_s2"], (v_c - self.V) / 2.0))
                a_t = alpha_trim * (v_cruise / V) ** 2 / max(0.3, math.cos(self.phi))
                a_t = max(-0.1, min(0.25, a_t))
                if math.cos(self.gamma) > 0.5:
                    self.psi += self.g * math.tan(self.phi) / V * dt
                self.phi += dphi * dt
                self.gamma += dgam * dt
                self.V += dv * dt
                self.alpha += (a_t - self.alpha) * dt / 1.0
                self.wind_gain = min(1.0, self.wind_gain + dt / F["wind_capture_s"])
            # position
            if ph != "rest":
                if self.k % 50 == 0:
                    self._radii = radii_m(self.lat)
                r_m, r_n = self._radii
                self.lat += vn / (r_m + self.h) * dt
                self.lon += ve / ((r_n + self.h) * math.cos(self.lat)) * dt
                self.h -= vd * dt
                if abs(self.lat) > math.radians(POLE_GUARD_DEG):
                    raise ValueError("the flight passes within ~1 km of a geographic pole, where the NED "
                                     "frame is undefined; move the legs away from the pole")
                if self.lon > math.pi:
                    self.lon -= 2 * math.pi
                elif self.lon < -math.pi:
                    self.lon += 2 * math.pi
            self.k += 1
            self.t = self.k * dt
        return {
            "time_s": out[:, 0], "lat_rad": out[:, 1], "lon_rad": out[:, 2], "alt_m": out[:, 3],
            "vel_ned_m_s": out[:, 4:7], "air_ned_m_s": out[:, 7:10], "psi": out[:, 10], "gamma": out[:, 11],
            "phi": out[:, 12], "alpha": out[:, 13], "phase": phase_out,
        }
