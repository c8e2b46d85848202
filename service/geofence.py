"""Geofence: dead-reckoned position, predicted breach with its uncertainty, latch, ordered actions.

METHODS.md A.9 (seed 000, claims 12-13): divert (or terminate) the platform when its azimuth shows
it leaving its allowed flight area. With GNSS gone, the position is dead-reckoned on our own
heading (estimators/dead_reckoning.py) and measured against the fence on the ellipsoid
(estimators/geodesy.py). No sockets, no clock: the daemon drives :class:`GeofenceMonitor` and
sends the :class:`~mavlink_io.commands.CommandSpec` it returns through a
:class:`~mavlink_io.commands.CommandProtocol`.

Per update (``update_hz``, FC time):
1. position: while the FC's GNSS is healthy, the FC's position (GLOBAL_POSITION_INT) is the fix
   and the wind is estimated (FC ground velocity - our air velocity); when it is lost, dead
   reckoning runs from the last trusted fix (or from the launch site if GNSS never was healthy);
2. fence in the vehicle-centred gnomonic plane (distances to every edge on the ellipsoid);
3. prediction along the current ground track at t = 0, 1, ..., lookahead_s:
       p(t) = v_gnd t,   P(t) = the dead-reckoning covariance propagated with the same inputs
       clearance(t) = d(p(t)) - margin - k sqrt(n^T P(t) n) - r_unknown(t)
   d: signed distance to the allowed area (> 0 inside: min over inclusion polygons and corridor,
   minus distance into exclusion polygons), n: unit vector to the nearest fence point,
   r_unknown: the radius from steps without heading or airspeed (grows at V_max + |w| while they
   stay unknown); the vertical clearance is min(h - h_min, h_max - h) - alt_margin - k sigma_h at
   h(t) = h + h_dot t. A breach is predicted when any clearance(t) <= 0: the fence is inside
   the uncertainty margin, not only when the mean crosses. time_to_breach = the first such t;
   Input age: the solution describes the vehicle ``a`` seconds ago when the daemon processes it
   late (a backlog in its socket on a loaded CPU). a = (local now - t_fc) - min over the flight
   of (local now - t_fc): the minimum is the offset of the two clocks with no queue (the
   one-way-delay floor, as NTP takes its best sample), so ``a`` is the queueing delay on top
   (drift of a crystal, 1e-4, adds 0.02 s over 200 s). The prediction runs over
   t = a, a + 1, ..., a + lookahead_s (the vehicle has flown on along its track meanwhile, and
   P(t) grows with it): a late daemon diverts at the time a prompt one would, or earlier.
   time_to_breach is counted from now (t - a). A late monitor says so (geofence_input_late).
   Lost packets add no age; a sender clock that pauses (a starved simulator) reads as late by the
   pause from then on (conservative);
4. hysteresis: a predicted breach held for ``trigger_hold_s`` latches the breach; the latch clears
   only when the clearance now exceeds ``clear_distance_m`` with no predicted breach for
   ``clear_hold_s``;
5. actions, only while armed (FC HEARTBEAT) and in flight (NavSolution.phase == "in-flight"):
   ``actions[0]`` when the latch sets; the next one when a command is denied or times out, or
   when the estimated position is still outside the fence ``escalate_after_s`` after an accepted
   one. "terminate" only with ``allow_termination`` (config validation enforces it).

Events (``drain_events()``) go to Zenoh ``events`` and, as STATUSTEXT, to the FC/GCS;
``state()`` is the Zenoh ``geofence`` payload.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from estimators.dead_reckoning import (DrInputs, DrParams, DrState, WindEstState, dr_init, dr_predict_covariance,
                                       dr_sigmas, dr_step, horizontal_airspeed_m_s, wind_estimate_sigma_m_s,
                                       wind_estimate_step)
from estimators.geodesy import LocalGnomonic, signed_distance_polygon, vincenty_direct
from mavlink_io.commands import (CommandOutcome, CommandSpec, cmd_reposition, cmd_rtl, cmd_set_mode,
                                 cmd_terminate)
from service.geofence_config import GeofenceConfig

SCHEMA = "azimuthd.geofence/1"
WIND_SETTLE_S = 5.0
"""The wind is estimated only from this long after the launch (off the launcher, wind captured)."""
WIND_MIN_TAS_M_S = 8.0
WIND_MIN_SPAN_S = 10.0
"""The estimated wind replaces the configured one once it averages over this long."""
STATES = ("inactive", "ok", "warning", "breach")
INPUT_LATE_WARN_S = 2.0
"""Input age above which the monitor warns (geofence_input_late); it says so again below half of it."""


@dataclass(frozen=True)
class GeofenceEvent:
    kind: str
    """geofence_dr_start | geofence_warning | geofence_breach | geofence_action | geofence_outcome |
    geofence_escalate | geofence_clear | geofence_no_action | geofence_heading_unknown | geofence_input_late"""
    severity: str
    """MAV_SEVERITY name: critical, warning, notice, info."""
    text: str
    """Short (<= 50 characters: it is also the STATUSTEXT)."""
    time_fc_s: float
    fields: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The Zenoh ``events`` payload (schema azimuthd.geofence/1)."""
        return {"schema": SCHEMA, "kind": self.kind, "severity": self.severity, "text": self.text,
                "time_fc_s": self.time_fc_s, **self.fields}


@dataclass(frozen=True)
class Evaluation:
    clearance_now_m: float
    """Clearance at t = 0 (after margin, k sigma and unknown radius); +inf with no limit."""
    distance_to_fence_m: float
    """Signed horizontal distance of the mean to the allowed area's boundary (> 0 inside)."""
    alt_clearance_m: float
    time_to_breach_s: float | None
    sigma_toward_fence_m: float


def corridor_polygon(home_lat_deg: float, home_lon_deg: float, azimuth_deg: float, half_width_deg: float,
                     range_m: float, home_radius_m: float, arc_step_deg: float = 5.0) -> tuple:
    """The azimuth corridor as a polygon (lat_deg, lon_deg): the wedge azimuth +/- half_width from
    the launch site out to range_m, joined to a disc of home_radius_m around the launch site (so
    the launch site itself is inside). Vertices on geodesics from the launch site."""
    lat0, lon0 = math.radians(home_lat_deg), math.radians(home_lon_deg)
    a0, a1 = azimuth_deg - half_width_deg, azimuth_deg + half_width_deg

    def pt(az_deg, r):
        la, lo = vincenty_direct(lat0, lon0, math.radians(az_deg % 360.0), r)
        return (math.degrees(la), math.degrees(lo))

    verts = [pt(a0, home_radius_m)]
    n_far = max(2, int(math.ceil((a1 - a0) / arc_step_deg)) + 1)
    verts += [pt(a, range_m) for a in np.linspace(a0, a1, n_far)]
    n_back = max(3, int(math.ceil((360.0 - (a1 - a0)) / arc_step_deg)) + 1)
    verts += [pt(a, home_radius_m) for a in np.linspace(a1, a0 + 360.0, n_back)[:-1]]
    return tuple(verts)


class GeofenceMonitor:
    """Holds the dead-reckoning state, the latch and the action sequence. Single-threaded."""

    def __init__(self, cfg: GeofenceConfig, home_lat_deg: float, home_lon_deg: float, home_alt_m: float,
                 dr_params: DrParams | None = None):
        """home: the launch site (config [site]); heights of the fence are relative to home_alt_m."""
        for name, v in (("home_lat_deg", home_lat_deg), ("home_lon_deg", home_lon_deg), ("home_alt_m", home_alt_m)):
            if v is None or not math.isfinite(v):
                raise ValueError(f"GeofenceMonitor needs a finite {name} (config site.*), got {v!r}")
        self.cfg = cfg
        self.home = (float(home_lat_deg), float(home_lon_deg), float(home_alt_m))
        self.dr_params = dataclasses.replace(dr_params or DrParams(), max_airspeed_m_s=cfg.max_airspeed_m_s)
        incl = [np.radians(np.array(p)) for p in cfg.inclusion]
        if cfg.corridor_azimuth_deg is not None:
            incl.append(np.radians(np.array(corridor_polygon(home_lat_deg, home_lon_deg, cfg.corridor_azimuth_deg,
                                                             cfg.corridor_half_width_deg, cfg.corridor_range_m,
                                                             cfg.corridor_home_radius_m))))
        self._incl = incl
        self._excl = [np.radians(np.array(p)) for p in cfg.exclusion]
        self._period_s = 1.0 / cfg.update_hz
        n = max(2, int(round(cfg.lookahead_s)) + 1)
        self._t_pred = np.linspace(0.0, cfg.lookahead_s, n)
        # inputs
        self.armed: bool | None = None
        self.autopilot: str | None = None
        self.vehicle_type = 1
        self.gnss_healthy = False
        self._fix: tuple | None = None   # (time_fc_s, lat_rad, lon_rad, alt_m, vn, ve)
        self._wind = WindEstState()
        self._press_alt_launch_m: float | None = None
        self._last_press_alt_m: float | None = None
        # state
        self.dr: DrState | None = None
        self.position_source = "none"
        self.state_name = "inactive"
        self.latched = False
        self._pred_since_s: float | None = None
        self._clear_since_s: float | None = None
        self._next_update_s = -math.inf
        self._last_eval: Evaluation | None = None
        self._last_time_s: float | None = None
        self._action_idx = -1
        self._action_status = "none"
        self._action_accepted_s: float | None = None
        self._outside_since_s: float | None = None
        self._events: list[GeofenceEvent] = []
        self._heading_known = True
        self._alt_min_armed = False
        self._flight_start_s: float | None = None
        self._clock_offset_min_s = math.inf
        self.input_age_s = 0.0
        """How late the last solution was processed (s, the module docstring's ``a``)."""
        self._input_late = False
        self.alt_reference = "none"
        self.counters = {"updates": 0, "breaches": 0, "actions_sent": 0, "clears": 0}
        self.actions_enabled = True
        """False after MAV_CMD_DO_FENCE_ENABLE 0 to our component: the monitor keeps dead reckoning
        and predicting (and says so) but sends no divert until enabled again."""

    # --- inputs from the daemon ------------------------------------------------------------

    def on_heartbeat(self, hb) -> None:
        """FcHeartbeat from the autopilot: armed flag, autopilot family, vehicle type."""
        self.armed = bool(hb.armed)
        self.autopilot = hb.autopilot
        self.vehicle_type = int(hb.vehicle_type)

    def on_gnss_health(self, healthy: bool) -> None:
        """GNSS health from FcSysStatus.gps_healthy and/or FcEkfStatus.horiz_pos_ok (both, ANDed,
        when the FC sends both): the FC's position is trusted only while this is True."""
        self.gnss_healthy = bool(healthy)

    def on_fc_position(self, time_fc_s: float, lat_deg: float, lon_deg: float, alt_m: float,
                       vn_m_s: float, ve_m_s: float) -> None:
        """GLOBAL_POSITION_INT (lat/lon degE7 -> deg, alt mm -> m AMSL, vx/vy cm/s -> m/s).
        Used only while GNSS is healthy."""
        vals = (time_fc_s, lat_deg, lon_deg, alt_m, vn_m_s, ve_m_s)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            return
        if not self.gnss_healthy:
            return
        self._fix = (float(time_fc_s), math.radians(lat_deg), math.radians(lon_deg), float(alt_m),
                     float(vn_m_s), float(ve_m_s))

    def on_command_outcome(self, outcome: CommandOutcome, time_fc_s: float | None = None) -> list[CommandSpec]:
        """An outcome from the CommandProtocol; returns the next action to send (if any)."""
        t = self._last_time_s if time_fc_s is None else time_fc_s
        t = 0.0 if t is None else t
        if self._action_idx < 0 or outcome.name != self.cfg.actions[self._action_idx]:
            return []  # not the action in progress (an older one, or not the geofence's)
        sev = "notice" if outcome.status == "accepted" else "critical"
        self._event("geofence_outcome", sev, f"fence {outcome.name}: {outcome.status} {outcome.result_name}"[:50], t,
                    action=outcome.name, status=outcome.status, result=outcome.result, tries=outcome.tries)
        if outcome.status == "accepted":
            self._action_status = "accepted"
            self._action_accepted_s = t
            return []
        if outcome.status == "superseded":
            self._action_status = "superseded"
            return []
        self._action_status = outcome.status
        if self.latched:
            return self._next_action(t, f"{outcome.name} {outcome.status}")
        return []

    # --- the update ------------------------------------------------------------------------

    def step(self, sol, air_data, now_s: float) -> list[CommandSpec]:
        """One NavSolution (any rate; the monitor updates at update_hz of FC time) and the latest
        AirData (estimators.air_data; None if none). now_s: local monotonic time, for the input
        age only (a replay passes the FC time: age 0); events carry FC time. Returns the commands
        to submit, in order."""
        t = float(sol.time_fc_s)
        if self._last_time_s is not None and t < self._last_time_s:
            self._clock_offset_min_s = math.inf  # a new FC clock: a new offset
        offset = float(now_s) - t
        self._clock_offset_min_s = min(self._clock_offset_min_s, offset)
        self.input_age_s = offset - self._clock_offset_min_s
        if air_data is not None and math.isfinite(air_data.pressure_altitude_m):
            self._last_press_alt_m = air_data.pressure_altitude_m
            if sol.phase in ("boot", "pre-launch"):
                self._press_alt_launch_m = air_data.pressure_altitude_m  # the launch site's baro reference
        if self._last_time_s is not None and t < self._last_time_s:
            # FC clock went back (reboot): restart from scratch, keep the latch
            self.dr = None
            self._next_update_s = -math.inf
        self._last_time_s = t
        if t < self._next_update_s:
            return []
        self._next_update_s = t + self._period_s * (1.0 - 1e-3)  # float-safe: a 10 Hz feed is not skipped
        flying = sol.phase in ("launch", "in-flight")
        if not flying:
            self.dr = None
            self._alt_min_armed = False
            self._flight_start_s = None
            self.position_source = "none"
            self.state_name = "inactive"
            return []
        self.counters["updates"] += 1
        if self._flight_start_s is None:
            self._flight_start_s = t
        if self.input_age_s > INPUT_LATE_WARN_S and not self._input_late:
            self._input_late = True
            self._event("geofence_input_late", "warning",
                        f"fence: input {self.input_age_s:.1f} s late, predicting from it", t,
                        input_age_s=self.input_age_s)
        elif self._input_late and self.input_age_s < 0.5 * INPUT_LATE_WARN_S:
            self._input_late = False
            self._event("geofence_input_late", "info", "fence: input on time again", t,
                        input_age_s=self.input_age_s)
        inp = self._inputs(sol, air_data, t)
        self._update_position(inp, t)
        ev = self._evaluate(inp)
        self._last_eval = ev
        return self._decide(ev, sol, t)

    # --- internals -------------------------------------------------------------------------

    def _heading(self, sol) -> tuple[float | None, float | None]:
        ok = (sol.heading_valid and sol.heading_rad is not None and sol.heading_sigma_rad is not None
              and math.isfinite(sol.heading_rad) and math.isfinite(sol.heading_sigma_rad)
              and sol.heading_sigma_rad <= math.radians(self.cfg.heading_sigma_max_deg))
        return (float(sol.heading_rad), float(sol.heading_sigma_rad)) if ok else (None, None)

    def _inputs(self, sol, air_data, t: float) -> DrInputs:
        hdg, hdg_sigma = self._heading(sol)
        tas = None
        alt_rate = 0.0
        tas_sigma = self.cfg.tas_sigma_m_s
        if air_data is not None and not (air_data.pitot_blocked or air_data.pitot_noisy) \
                and math.isfinite(air_data.tas_m_s):
            tas = float(air_data.tas_m_s)
            tas_sigma = math.hypot(tas_sigma, air_data.tas_noise_std_m_s)
            alt_rate = float(air_data.alt_rate_m_s) if air_data.rate_valid else 0.0
        alt = None
        if self._last_press_alt_m is not None:
            if self._press_alt_launch_m is not None:
                alt = self.home[2] + (self._last_press_alt_m - self._press_alt_launch_m)
                self.alt_reference = "launch"
            else:
                # no baro sample on the launcher (daemon started in flight): ISA pressure altitude,
                # off by the day's QNH deviation (~8 m per hPa); reported in state()
                alt = self._last_press_alt_m
                self.alt_reference = "isa"
        wind, wind_sigma = self._wind_now(hdg, hdg_sigma, tas, alt_rate, t)
        if (hdg is None) == self._heading_known:
            self._heading_known = hdg is not None
            if hdg is None:
                self._event("geofence_heading_unknown", "warning", "fence: heading unknown, DR radius grows", t)
            else:
                self._event("geofence_heading_unknown", "info", "fence: heading back", t)
        return DrInputs(time_s=t, heading_rad=hdg, heading_sigma_rad=hdg_sigma, tas_m_s=tas,
                        tas_sigma_m_s=tas_sigma, wind_ne_m_s=wind, wind_sigma_m_s=wind_sigma, alt_m=alt,
                        alt_rate_m_s=alt_rate)

    def _wind_now(self, hdg, hdg_sigma, tas, alt_rate, t: float) -> tuple[tuple[float, float], float]:
        cfg = self.cfg
        if cfg.wind_source == "estimate":
            settled = self._flight_start_s is not None and t - self._flight_start_s >= WIND_SETTLE_S
            if (self.gnss_healthy and self._fix is not None and hdg is not None and tas is not None
                    and tas >= WIND_MIN_TAS_M_S and settled and self._wind.time_s != self._fix[0]):
                vh = horizontal_airspeed_m_s(tas, alt_rate)
                self._wind = wind_estimate_step(self._wind, self._fix[0], (self._fix[4], self._fix[5]), hdg, vh)
            if self._wind.time_s is not None and self._wind.duration_s >= WIND_MIN_SPAN_S:
                vh = horizontal_airspeed_m_s(tas or 0.0, alt_rate)
                return self._wind.wind_ne_m_s, wind_estimate_sigma_m_s(self._wind, hdg_sigma or 0.0, vh,
                                                                       cfg.wind_sigma_min_m_s)
        return (cfg.wind_north_m_s, cfg.wind_east_m_s), cfg.wind_sigma_m_s

    def _update_position(self, inp: DrInputs, t: float) -> None:
        cfg = self.cfg
        s_psi, s_V, s_w = dr_sigmas(inp, self.dr_params)
        if self.gnss_healthy and self._fix is not None and t - self._fix[0] < 2.0:
            _tf, la, lo, alt, vn, ve = self._fix
            self.dr = dr_init(t, la, lo, inp.alt_m if inp.alt_m is not None else alt, cfg.fix_sigma_m,
                              s_psi, s_V, s_w)
            self.dr = dataclasses.replace(self.dr, v_ground_ne_m_s=(vn, ve))  # the FC's ground velocity
            if self.position_source != "gnss":
                self._event("geofence_dr_start", "info", "fence: position from FC GNSS", t)
            self.position_source = "gnss"
            return
        if self.dr is None:
            if self._fix is not None:
                _tf, la, lo, alt, _vn, _ve = self._fix
                src, why = "dead_reckoning", "fence: GNSS lost, DR from last fix"
            else:
                la, lo, alt = math.radians(self.home[0]), math.radians(self.home[1]), self.home[2]
                src, why = "dead_reckoning", "fence: DR from launch site"
            self.dr = dr_init(t, la, lo, inp.alt_m if inp.alt_m is not None else alt, cfg.fix_sigma_m, s_psi, s_V, s_w)
            self.position_source = src
            self._event("geofence_dr_start", "notice", why, t)
        elif self.position_source == "gnss":
            self.position_source = "dead_reckoning"
            self._event("geofence_dr_start", "notice", "fence: GNSS lost, DR from last fix", t)
        self.dr, _ = dr_step(self.dr, inp, self.dr_params)

    def _signed_distance(self, plane: LocalGnomonic, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K,) signed distance to the allowed area and (K, 2) unit vectors toward the nearest fence
        point, for planar points in the vehicle-centred gnomonic plane."""
        K = pts.shape[0]
        best = np.full(K, np.inf)
        nvec = np.zeros((K, 2))
        for poly in self._incl:
            d, n = signed_distance_polygon(pts, plane.forward(poly[:, 0], poly[:, 1]))
            m = d < best
            best[m], nvec[m] = d[m], n[m]
        for poly in self._excl:
            d, n = signed_distance_polygon(pts, plane.forward(poly[:, 0], poly[:, 1]))
            d = -d
            m = d < best
            best[m], nvec[m] = d[m], n[m]
        finite = np.isfinite(best)
        best[finite] = plane.plane_to_surface_distance_m(best[finite])
        return best, nvec

    def _evaluate(self, inp: DrInputs) -> Evaluation:
        cfg, dr = self.cfg, self.dr
        t = self._t_pred + self.input_age_s  # since the solution's FC time (its age, then the look-ahead)
        k = cfg.sigma_k
        vN, vE = dr.v_ground_ne_m_s
        moving = inp.heading_rad is not None and inp.tas_m_s is not None
        s_psi, s_V, s_w = dr_sigmas(inp, self.dr_params)
        if moving:
            v_h = horizontal_airspeed_m_s(inp.tas_m_s, inp.alt_rate_m_s)
            Pk = dr_predict_covariance(dr.P, inp.heading_rad, v_h, (s_psi, s_V, s_w), t, self.dr_params)
            r_unknown = np.full_like(t, dr.unknown_radius_m)
        elif self.position_source == "gnss":
            # the FC's velocity is known; our heading is not: predict on the FC's track
            Pk = dr_predict_covariance(dr.P, math.atan2(vE, vN), math.hypot(vN, vE), (s_psi, s_V, s_w), t,
                                       self.dr_params)
            r_unknown = np.zeros_like(t)
        else:
            vN = vE = 0.0
            Pk = dr_predict_covariance(dr.P, 0.0, 0.0, (s_psi, s_V, s_w), t, self.dr_params)
            grow = self.dr_params.max_airspeed_m_s + math.hypot(*inp.wind_ne_m_s) + 3.0 * s_w
            r_unknown = dr.unknown_radius_m + grow * t
        clear = np.full_like(t, np.inf)
        d_now = math.inf
        sig_n0 = 0.0
        if self._incl or self._excl:
            plane = LocalGnomonic(dr.lat_rad, dr.lon_rad)
            pts = np.stack([vE * t, vN * t], axis=1)  # plane x = east, y = north
            d, n = self._signed_distance(plane, pts)
            nNE = np.stack([n[:, 1], n[:, 0]], axis=1)
            sig_n = np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", nNE, Pk, nNE), 0.0))
            clear = d - cfg.margin_m - k * sig_n - r_unknown
            d_now, sig_n0 = float(d[0]), float(sig_n[0])
        alt_clear = math.inf
        if cfg.alt_min_m is not None or cfg.alt_max_m is not None:
            h = (dr.alt_m - self.home[2]) + inp.alt_rate_m_s * t
            c = np.full_like(t, np.inf)
            if cfg.alt_min_m is not None:
                if not self._alt_min_armed and dr.alt_m - self.home[2] >= cfg.alt_min_m + cfg.alt_margin_m + k * cfg.alt_sigma_m:
                    self._alt_min_armed = True  # the floor applies once the vehicle HAS climbed above it (not a prediction)
                if self._alt_min_armed:
                    c = np.minimum(c, h - cfg.alt_min_m)
            if cfg.alt_max_m is not None:
                c = np.minimum(c, cfg.alt_max_m - h)
            c = c - cfg.alt_margin_m - k * cfg.alt_sigma_m
            alt_clear = float(c[0])
            clear = np.minimum(clear, c)
        bad = np.nonzero(clear <= 0.0)[0]
        ttb = float(self._t_pred[bad[0]]) if bad.size else None  # from now
        return Evaluation(clearance_now_m=float(clear[0]), distance_to_fence_m=d_now, alt_clearance_m=alt_clear,
                          time_to_breach_s=ttb, sigma_toward_fence_m=sig_n0)

    def _decide(self, ev: Evaluation, sol, t: float) -> list[CommandSpec]:
        cfg = self.cfg
        predicted = ev.time_to_breach_s is not None
        out: list[CommandSpec] = []
        if predicted:
            self._clear_since_s = None
            if self._pred_since_s is None:
                self._pred_since_s = t
                if not self.latched:
                    self._event("geofence_warning", "warning",
                                f"fence: breach in {ev.time_to_breach_s:.0f} s predicted", t,
                                time_to_breach_s=ev.time_to_breach_s, clearance_m=ev.clearance_now_m)
            if not self.latched and t - self._pred_since_s >= cfg.trigger_hold_s - 1e-9:
                self.latched = True
                self.counters["breaches"] += 1
                self._action_idx = -1
                self._outside_since_s = None
                self._event("geofence_breach", "critical",
                            f"FENCE BREACH in {ev.time_to_breach_s:.0f}s: divert", t,
                            time_to_breach_s=ev.time_to_breach_s, clearance_m=ev.clearance_now_m,
                            distance_to_fence_m=ev.distance_to_fence_m, source=self.position_source)
                out += self._next_action(t, "breach predicted")
        else:
            self._pred_since_s = None
            if self.latched:
                if ev.clearance_now_m >= cfg.clear_distance_m:
                    if self._clear_since_s is None:
                        self._clear_since_s = t
                    if t - self._clear_since_s >= cfg.clear_hold_s - 1e-9:
                        self.latched = False
                        self.counters["clears"] += 1
                        self._action_idx = -1
                        self._action_status = "none"
                        self._event("geofence_clear", "notice", "fence: well inside again, latch cleared", t,
                                    clearance_m=ev.clearance_now_m)
                else:
                    self._clear_since_s = None
        # escalation: the action was accepted but the estimated position is outside the fence
        outside = ev.distance_to_fence_m < 0 or (ev.alt_clearance_m + cfg.alt_margin_m + cfg.sigma_k * cfg.alt_sigma_m) < 0
        if self.latched and outside:
            if self._outside_since_s is None:
                self._outside_since_s = t
        else:
            self._outside_since_s = None
        if (self.latched and self._action_status == "accepted" and self._action_accepted_s is not None
                and self._outside_since_s is not None
                and t - max(self._action_accepted_s, self._outside_since_s) >= cfg.escalate_after_s):
            out += self._next_action(t, "still outside after the accepted action")
        if self.latched and self._action_idx < 0 and not out:
            out += self._next_action(t, "breach latched")  # armed/in-flight arrived after the latch
        self.state_name = "breach" if self.latched else ("warning" if predicted else "ok")
        return out

    def _may_act(self, t: float) -> tuple[bool, str]:
        if not self.actions_enabled:
            return False, "disabled by command"
        if self.cfg.require_armed and self.armed is not True:
            return False, "FC not armed" if self.armed is False else "FC armed state unknown"
        return True, ""

    def _next_action(self, t: float, why: str) -> list[CommandSpec]:
        ok, reason = self._may_act(t)
        if not ok:
            if self._action_status != f"blocked: {reason}":
                self._event("geofence_no_action", "warning", f"fence: no action, {reason}"[:50], t)
            self._action_status = f"blocked: {reason}"
            return []
        nxt = self._action_idx + 1
        if nxt >= len(self.cfg.actions):
            if self._action_status != "exhausted":
                self._event("geofence_no_action", "critical", "fence: every action tried", t)
            self._action_status = "exhausted"
            return []
        self._action_idx = nxt
        name = self.cfg.actions[nxt]
        spec = self._spec(name)
        self._action_status = "sent"
        self._action_accepted_s = None
        self.counters["actions_sent"] += 1
        kind = "geofence_action" if nxt == 0 else "geofence_escalate"
        self._event(kind, "critical", f"fence: {name} ({why})"[:50], t, action=name, reason=why)
        return [spec]

    def _spec(self, name: str) -> CommandSpec:
        cfg = self.cfg
        if name == "rtl":
            spec = cmd_rtl()
        elif name in ("rtl_mode", "loiter_mode"):
            spec = cmd_set_mode(name.split("_")[0], self.autopilot, self.vehicle_type)
        elif name == "reposition":
            spec = cmd_reposition(cfg.safe_lat_deg, cfg.safe_lon_deg, cfg.safe_alt_m)
        elif name == "terminate":
            if not cfg.allow_termination:
                raise ValueError("terminate without allow_termination")  # config validation prevents this
            spec = cmd_terminate()
        else:
            raise ValueError(f"unknown action {name!r}")
        return CommandSpec(name, spec.command, spec.params, spec.use_int, spec.frame)

    def _event(self, kind: str, severity: str, text: str, t: float, **fields) -> None:
        self._events.append(GeofenceEvent(kind, severity, text[:50], t, fields))

    # --- outputs ---------------------------------------------------------------------------

    def drain_events(self) -> list[GeofenceEvent]:
        ev, self._events = self._events, []
        return ev

    def state(self) -> dict:
        """The Zenoh ``geofence`` payload (units in the keys)."""
        dr, ev = self.dr, self._last_eval
        out = {"schema": SCHEMA, "time_fc_s": self._last_time_s, "state": self.state_name, "latched": self.latched,
               "position_source": self.position_source, "armed": self.armed, "gnss_healthy": self.gnss_healthy,
               "alt_reference": self.alt_reference,
               "action": self.cfg.actions[self._action_idx] if self._action_idx >= 0 else None,
               "action_status": self._action_status}
        if dr is not None:
            evals = np.linalg.eigvalsh(dr.P[0:2, 0:2])
            out.update({"lat_deg": math.degrees(dr.lat_rad), "lon_deg": math.degrees(dr.lon_rad),
                        "alt_m": dr.alt_m, "pos_sigma_major_m": math.sqrt(max(evals[1], 0.0)),
                        "pos_sigma_minor_m": math.sqrt(max(evals[0], 0.0)),
                        "unknown_radius_m": dr.unknown_radius_m, "dr_distance_m": dr.distance_m,
                        "ground_velocity_ned_m_s": [dr.v_ground_ne_m_s[0], dr.v_ground_ne_m_s[1], None]})
        if ev is not None:
            out.update({"distance_to_fence_m": _finite_or_none(ev.distance_to_fence_m),
                        "clearance_m": _finite_or_none(ev.clearance_now_m),
                        "alt_clearance_m": _finite_or_none(ev.alt_clearance_m),
                        "time_to_breach_s": ev.time_to_breach_s,
                        "sigma_toward_fence_m": ev.sigma_toward_fence_m})
        return out

    @property
    def evaluation(self) -> Evaluation | None:
        return self._last_eval


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


__all__ = ["GeofenceMonitor", "GeofenceEvent", "Evaluation", "corridor_polygon", "SCHEMA"]
