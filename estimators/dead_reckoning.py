"""Dead reckoning on our own heading, air data and a wind vector, with an honest position covariance.

METHODS.md A.9 (claims 12-13 of seed 000): with GNSS gone, the position that tells whether the
platform is leaving its flight area comes from dead reckoning on the azimuth/heading we estimate.

Mean (horizontal; altitude comes from the barometer):
    v_air_NE = V_h [cos psi, sin psi],     V_h = TAS cos(gamma),  sin(gamma) = h_dot / TAS
    v_gnd_NE = v_air_NE + w_NE
    lat_dot  = v_N / (M + h),   lon_dot = v_E / ((N + h) cos lat)      (geodesy.radii_m)
The heading is that of the body x axis; in coordinated flight the air velocity is along it (the
crab angle is the wind's, and the wind is added explicitly). Sideslip is folded into the heading
sigma (``sideslip_sigma_rad``).

Error state (6): x = [dp_N, dp_E, d_psi, d_V, dw_N, dw_E], linearised about the mean:
    d(dp)/dt = J_psi d_psi + J_V d_V + dw,   J_psi = V_h [-sin psi, cos psi],  J_V = [cos psi, sin psi]
    d(d_psi)/dt = -d_psi / tau_psi + n_psi,  d(d_V)/dt = -d_V / tau_V + n_V,
    d(dw)/dt = -dw / tau_w + n_w             (first-order Gauss-Markov, stationary sigmas)
Heading, airspeed and wind errors are NOT white: over a look-ahead they act almost as biases, so a
position error grows ~ linearly in time (sigma_psi V t), not as sqrt(t). Treating them as white
noise would shrink the fence margin dishonestly; the Gauss-Markov states keep the correlation.
Discretisation: Phi = I + F dt + F^2 dt^2 / 2 (F^3 = 0 for the position rows' coupling at this
order; dt <= 0.5 s), Q = diag(0, 0, 2 s_psi^2/tau_psi, 2 s_V^2/tau_V, 2 s_w^2/tau_w, ...) dt.

The heading sigma the heading source reports changes with time. After propagation the d_psi
variance is set to the reported sigma^2; its cross-covariances with the position are scaled by
min(1, sigma_new / sigma_old) (a better heading is less correlated with the past position error;
a worse one adds fresh, uncorrelated error). The same for the airspeed sigma and the wind sigma.

Unknown inputs: a step without a valid heading or airspeed cannot move the mean. The true position
then lies within ``unknown_radius_m`` of the mean, which grows by (V_max + |w| + 3 sigma_w) dt per
such step (V_max: ``max_airspeed_m_s``); it never shrinks until a trusted fix resets the state.

Pure: ``dr_init(...) -> DrState``, ``dr_step(state, inputs, params) -> (state, DrDiag)``,
``dr_reset_to_fix(...)``; ``dr_predict_covariance(...)`` propagates the covariance over a
look-ahead with constant inputs (breach prediction).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.geodesy import radii_m

N_ERR = 6
I_PN, I_PE, I_PSI, I_V, I_WN, I_WE = range(N_ERR)


@dataclass(frozen=True)
class DrParams:
    tau_heading_s: float = 120.0
    """Correlation time of the heading error (gyro drift, magnetic deviation: minutes)."""
    tau_airspeed_s: float = 60.0
    """Correlation time of the airspeed error (pitot calibration, density)."""
    tau_wind_s: float = 600.0
    """Correlation time of the wind error (the wind changes over ten minutes and more)."""
    sideslip_sigma_rad: float = math.radians(2.0)
    """1-sigma angle between the body x axis and the air velocity, added to the heading sigma."""
    max_airspeed_m_s: float = 40.0
    """Upper bound on the true airspeed, used when heading or airspeed is unknown."""
    max_dt_s: float = 0.5
    """A longer step is split (the discretisation is second order)."""
    predict_dt_s: float = 1.0
    """Step of the look-ahead covariance prediction (constant inputs: 1 s keeps it within 0.3 %)."""

    def __post_init__(self):
        for name in ("tau_heading_s", "tau_airspeed_s", "tau_wind_s", "max_airspeed_m_s", "max_dt_s", "predict_dt_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"DrParams.{name} must be finite and > 0, got {v!r}")
        if not (math.isfinite(self.sideslip_sigma_rad) and self.sideslip_sigma_rad >= 0):
            raise ValueError(f"DrParams.sideslip_sigma_rad must be finite and >= 0, got {self.sideslip_sigma_rad!r}")


@dataclass(frozen=True)
class DrInputs:
    """One dead-reckoning step's inputs (all at ``time_s``, FC clock)."""
    time_s: float
    heading_rad: float | None
    """True heading of the body x axis; None when no valid heading source."""
    heading_sigma_rad: float | None
    tas_m_s: float | None
    """True airspeed (air data); None when the pitot is unusable."""
    tas_sigma_m_s: float
    wind_ne_m_s: tuple[float, float]
    """Wind velocity (the direction it blows toward), north and east."""
    wind_sigma_m_s: float
    """1-sigma error of each wind component."""
    alt_m: float | None = None
    """Barometric altitude (WGS-84 height of the vehicle from the baro); None keeps the last."""
    alt_rate_m_s: float = 0.0
    """Climb rate from air data (for the horizontal airspeed TAS cos(gamma))."""


@dataclass(frozen=True)
class DrState:
    time_s: float
    lat_rad: float
    lon_rad: float
    alt_m: float
    P: np.ndarray
    """(6, 6) error covariance of [dp_N, dp_E (m), d_psi (rad), d_V (m/s), dw_N, dw_E (m/s)]."""
    unknown_radius_m: float = 0.0
    """Extra radius (m) the position may be off by, from steps without heading or airspeed."""
    v_ground_ne_m_s: tuple[float, float] = (0.0, 0.0)
    """Ground velocity of the last step (north, east)."""
    distance_m: float = 0.0
    """Distance dead-reckoned since the fix."""
    fix_time_s: float = 0.0


@dataclass(frozen=True)
class DrDiag:
    sigma_pos_major_m: float
    sigma_pos_minor_m: float
    moved: bool
    """False when the step had no heading or airspeed (the unknown radius grew instead)."""


def dr_init(time_s: float, lat_rad: float, lon_rad: float, alt_m: float, pos_sigma_m: float,
            heading_sigma_rad: float, tas_sigma_m_s: float, wind_sigma_m_s: float) -> DrState:
    """Start dead reckoning at a fix (launch site or the last trusted FC position)."""
    for name, v in (("time_s", time_s), ("lat_rad", lat_rad), ("lon_rad", lon_rad), ("alt_m", alt_m)):
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
    if abs(lat_rad) >= math.radians(89.99):
        raise ValueError(f"dead reckoning in lat/lon is undefined at the pole; lat {math.degrees(lat_rad)} deg")
    for name, v in (("pos_sigma_m", pos_sigma_m), ("heading_sigma_rad", heading_sigma_rad),
                    ("tas_sigma_m_s", tas_sigma_m_s), ("wind_sigma_m_s", wind_sigma_m_s)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
    P = np.diag([pos_sigma_m ** 2, pos_sigma_m ** 2, heading_sigma_rad ** 2, tas_sigma_m_s ** 2,
                 wind_sigma_m_s ** 2, wind_sigma_m_s ** 2])
    return DrState(time_s=float(time_s), lat_rad=float(lat_rad), lon_rad=float(lon_rad), alt_m=float(alt_m),
                   P=P, fix_time_s=float(time_s))


def error_jacobians(heading_rad: float, v_h_m_s: float) -> tuple[np.ndarray, np.ndarray]:
    """d v_gnd / d psi and d v_gnd / d V for v_gnd = V [cos psi, sin psi] + w (NE)."""
    s, c = math.sin(heading_rad), math.cos(heading_rad)
    return np.array([-v_h_m_s * s, v_h_m_s * c]), np.array([c, s])


def transition(heading_rad: float, v_h_m_s: float, dt_s: float, params: DrParams) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, Q) of the error state over dt with constant inputs; Q without the sigma scaling
    (multiply Q's diagonal by the sigmas squared: returned as the per-unit-variance factors)."""
    J_psi, J_V = error_jacobians(heading_rad, v_h_m_s)
    F = np.zeros((N_ERR, N_ERR))
    F[0:2, I_PSI] = J_psi
    F[0:2, I_V] = J_V
    F[0:2, I_WN:I_WE + 1] = np.eye(2)
    F[I_PSI, I_PSI] = -1.0 / params.tau_heading_s
    F[I_V, I_V] = -1.0 / params.tau_airspeed_s
    F[I_WN, I_WN] = F[I_WE, I_WE] = -1.0 / params.tau_wind_s
    Fdt = F * dt_s
    Phi = np.eye(N_ERR) + Fdt + 0.5 * Fdt @ Fdt
    q = np.zeros(N_ERR)
    q[I_PSI] = 2.0 / params.tau_heading_s * dt_s
    q[I_V] = 2.0 / params.tau_airspeed_s * dt_s
    q[I_WN] = q[I_WE] = 2.0 / params.tau_wind_s * dt_s
    return Phi, q


def _rescale(P: np.ndarray, idx: list[int], sigma_new: float) -> None:
    """Set the variance of the states idx to sigma_new^2, scaling their cross-covariances by
    min(1, sigma_new / sigma_old) (in place)."""
    for i in idx:
        old = math.sqrt(max(P[i, i], 0.0))
        r = 1.0 if old <= 0.0 else min(1.0, sigma_new / old)
        P[i, :] *= r
        P[:, i] *= r
        P[i, i] = sigma_new * sigma_new


def _sigmas(inp: DrInputs, params: DrParams) -> tuple[float, float, float]:
    s_psi = math.hypot(inp.heading_sigma_rad or 0.0, params.sideslip_sigma_rad)
    return s_psi, float(inp.tas_sigma_m_s), float(inp.wind_sigma_m_s)


def _check(inp: DrInputs) -> None:
    if not math.isfinite(inp.time_s):
        raise ValueError(f"DrInputs.time_s must be finite, got {inp.time_s!r}")
    if inp.heading_rad is not None and not (math.isfinite(inp.heading_rad)
                                            and inp.heading_sigma_rad is not None
                                            and math.isfinite(inp.heading_sigma_rad)
                                            and inp.heading_sigma_rad >= 0):
        raise ValueError(f"DrInputs heading {inp.heading_rad!r} needs a finite heading_sigma_rad >= 0, "
                         f"got {inp.heading_sigma_rad!r}")
    if inp.tas_m_s is not None and not (math.isfinite(inp.tas_m_s) and inp.tas_m_s >= 0):
        raise ValueError(f"DrInputs.tas_m_s must be finite and >= 0 or None, got {inp.tas_m_s!r}")
    for name in ("tas_sigma_m_s", "wind_sigma_m_s"):
        v = getattr(inp, name)
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"DrInputs.{name} must be finite and >= 0, got {v!r}")
    if len(inp.wind_ne_m_s) != 2 or not all(math.isfinite(w) for w in inp.wind_ne_m_s):
        raise ValueError(f"DrInputs.wind_ne_m_s must be two finite numbers, got {inp.wind_ne_m_s!r}")
    if inp.alt_m is not None and not math.isfinite(inp.alt_m):
        raise ValueError(f"DrInputs.alt_m must be finite or None, got {inp.alt_m!r}")


def horizontal_airspeed_m_s(tas_m_s: float, alt_rate_m_s: float) -> float:
    """V_h = TAS cos(gamma), sin(gamma) = h_dot / TAS (clamped to |gamma| <= 60 deg)."""
    if tas_m_s <= 0.0:
        return 0.0
    s = max(-0.866, min(0.866, alt_rate_m_s / tas_m_s))
    return tas_m_s * math.sqrt(1.0 - s * s)


def dr_step(state: DrState, inp: DrInputs, params: DrParams = DrParams()) -> tuple[DrState, DrDiag]:
    """Propagate the mean and the covariance from state.time_s to inp.time_s with inp's values."""
    _check(inp)
    dt_total = inp.time_s - state.time_s
    if dt_total < 0:
        raise ValueError(f"DrInputs.time_s must not go back: {inp.time_s!r} after {state.time_s!r}")
    s_psi, s_V, s_w = _sigmas(inp, params)
    P = state.P.copy()
    lat, lon, alt = state.lat_rad, state.lon_rad, state.alt_m
    wN, wE = (float(inp.wind_ne_m_s[0]), float(inp.wind_ne_m_s[1]))
    moved = inp.heading_rad is not None and inp.tas_m_s is not None
    unknown = state.unknown_radius_m
    dist = state.distance_m
    vN = vE = 0.0
    n_sub = max(1, math.ceil(dt_total / params.max_dt_s)) if dt_total > 0 else 0
    if moved:
        V = horizontal_airspeed_m_s(float(inp.tas_m_s), inp.alt_rate_m_s)
        psi = float(inp.heading_rad)
        vN, vE = V * math.cos(psi) + wN, V * math.sin(psi) + wE
    for _ in range(n_sub):
        dt = dt_total / n_sub
        if moved:
            M, N = radii_m(lat)
            lat_mid = lat + 0.5 * vN * dt / (M + alt)
            M, N = radii_m(lat_mid)
            lat = lat + vN * dt / (M + alt)
            lon = lon + vE * dt / ((N + alt) * math.cos(lat_mid))
            dist += math.hypot(vN, vE) * dt
            Phi, q = transition(psi, V, dt, params)
        else:
            # the mean stays; the truth can be anywhere within (V_max + |w| + 3 s_w) dt
            unknown += (params.max_airspeed_m_s + math.hypot(wN, wE) + 3.0 * s_w) * dt
            Phi, q = transition(0.0, 0.0, dt, params)
        q_scaled = q * np.array([0.0, 0.0, s_psi ** 2, s_V ** 2, s_w ** 2, s_w ** 2])
        P = Phi @ P @ Phi.T + np.diag(q_scaled)
    _rescale(P, [I_PSI], s_psi)
    _rescale(P, [I_V], s_V)
    _rescale(P, [I_WN, I_WE], s_w)
    P = 0.5 * (P + P.T)
    if inp.alt_m is not None:
        alt = float(inp.alt_m)
    lon = math.remainder(lon, 2 * math.pi)
    new = DrState(time_s=float(inp.time_s), lat_rad=lat, lon_rad=lon, alt_m=alt, P=P,
                  unknown_radius_m=unknown, v_ground_ne_m_s=(vN, vE) if moved else state.v_ground_ne_m_s,
                  distance_m=dist, fix_time_s=state.fix_time_s)
    ev = np.linalg.eigvalsh(P[0:2, 0:2])
    return new, DrDiag(sigma_pos_major_m=math.sqrt(max(ev[1], 0.0)), sigma_pos_minor_m=math.sqrt(max(ev[0], 0.0)),
                       moved=moved)


def dr_predict_covariance(P: np.ndarray, heading_rad: float, v_h_m_s: float, sigmas: tuple[float, float, float],
                          times_s: np.ndarray, params: DrParams = DrParams()) -> np.ndarray:
    """Position covariances (K, 2, 2) at the look-ahead times (s, increasing, >= 0) with constant
    inputs, starting from the error covariance P (6, 6). sigmas = (heading incl. sideslip, TAS, wind)."""
    s_psi, s_V, s_w = sigmas
    scale = np.array([0.0, 0.0, s_psi ** 2, s_V ** 2, s_w ** 2, s_w ** 2])
    out = np.empty((len(times_s), 2, 2))
    t_prev = 0.0
    Pk = P.copy()
    cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    for k, t in enumerate(times_s):
        dt = float(t) - t_prev
        if dt < 0:
            raise ValueError("times_s must increase")
        if dt > 0:
            n_sub = max(1, math.ceil(dt / params.predict_dt_s - 1e-9))
            h = dt / n_sub
            key = round(h, 9)
            if key not in cache:
                cache[key] = transition(heading_rad, v_h_m_s, h, params)
            Phi, q = cache[key]
            Q = np.diag(q * scale)
            for _ in range(n_sub):
                Pk = Phi @ Pk @ Phi.T + Q
        out[k] = Pk[0:2, 0:2]
        t_prev = float(t)
    return out


def dr_sigmas(inp: DrInputs, params: DrParams = DrParams()) -> tuple[float, float, float]:
    """The (heading incl. sideslip, TAS, wind) sigmas this step's inputs imply."""
    return _sigmas(inp, params)


@dataclass(frozen=True)
class WindEstState:
    wind_ne_m_s: tuple[float, float] = (0.0, 0.0)
    var_ne_m2_s2: tuple[float, float] = (0.0, 0.0)
    """Spread (variance) of the single-sample wind per component, (m/s)^2."""
    n: int = 0
    duration_s: float = 0.0
    """Time span the mean averages over (grows to tau_s)."""
    time_s: float | None = None


def wind_estimate_step(state: WindEstState, time_s: float, v_ground_ne_m_s: tuple[float, float],
                       heading_rad: float, v_h_m_s: float, tau_s: float = 60.0, max_gap_s: float = 5.0
                       ) -> WindEstState:
    """Wind = ground velocity (FC, GNSS healthy) - air velocity (our heading, horizontal TAS).

    Averaged with gain g = max(1/n, 1 - exp(-dt/tau_s)): the plain mean of the samples so far
    until it spans tau_s, then an exponential average with time constant tau_s (so the first
    sample does not dominate, and a changing wind is followed). A gap longer than max_gap_s
    restarts the average."""
    if not all(math.isfinite(x) for x in (time_s, *v_ground_ne_m_s, heading_rad, v_h_m_s)):
        raise ValueError("wind_estimate_step: non-finite input")
    w = (v_ground_ne_m_s[0] - v_h_m_s * math.cos(heading_rad), v_ground_ne_m_s[1] - v_h_m_s * math.sin(heading_rad))
    if state.time_s is None or time_s - state.time_s > max_gap_s or time_s < state.time_s:
        return WindEstState(w, (0.0, 0.0), 1, 0.0, time_s)
    dt = time_s - state.time_s
    n = state.n + 1
    g = max(1.0 / n, 1.0 - math.exp(-dt / tau_s))
    m_old = state.wind_ne_m_s
    m = tuple(m_old[i] + g * (w[i] - m_old[i]) for i in range(2))
    var = tuple(state.var_ne_m2_s2[i] + g * ((w[i] - m_old[i]) * (w[i] - m[i]) - state.var_ne_m2_s2[i])
                for i in range(2))
    return WindEstState(m, var, n, min(state.duration_s + dt, tau_s), time_s)


def wind_estimate_sigma_m_s(state: WindEstState, heading_sigma_rad: float, v_h_m_s: float,
                            floor_m_s: float, correlation_s: float = 5.0) -> float:
    """1-sigma of the estimated wind per component: the single-sample spread over the square root
    of the number of INDEPENDENT samples (duration / correlation_s: gusts and heading noise are
    correlated over seconds), plus V sigma_psi (a heading bias does not average out), at least
    floor_m_s."""
    n_ind = max(1.0, state.duration_s / correlation_s)
    spread = math.sqrt(max(max(state.var_ne_m2_s2), 0.0) / n_ind)
    return max(floor_m_s, math.hypot(spread, v_h_m_s * heading_sigma_rad))


__all__ = ["DrParams", "DrInputs", "DrState", "DrDiag", "dr_init", "dr_step", "dr_predict_covariance",
           "dr_sigmas", "error_jacobians", "transition", "horizontal_airspeed_m_s", "WindEstState",
           "wind_estimate_step", "wind_estimate_sigma_m_s"]
