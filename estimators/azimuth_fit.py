"""psi_s from in-flight magnetometer samples: closed forms, distortion fits, covariance, gate.

METHODS.md A steps 5-8 (seed AU2018311656B2, eq. 3-6 and 9.1-9.6). Frames:
NF = NED; ISF = sensor frame at launch; SF = sensor frame now; AF = auxiliary frame (z down,
x = horizontal projection of x_ISF). psi_s = angle from north to x_AF, so

    C_AF<-NF  = R3(psi_s)                       (R3 = frame rotation about down)
    C_ISF<-AF = R1(roll) R2(pitch)              (from levelling; ``C_isf_from_af``)
    M_i       = C_SF<-ISF(t_i) C_ISF<-AF        (gyro-propagated; "C_sf_from_af" below)
    m_i(psi)  = M_i R3(psi) e_NF                (undistorted field the sensor should see)

Derivation of eq. 5.3 -> psi_s (why ``psi = delta - atan2(h_y, h_x)``): R3(psi) e_NF has the
horizontal components |e_h| [cos(delta - psi), sin(delta - psi)], delta = atan2(e_E, e_N).

Measurement models (``model``), residual r_i = h_i - A m_i(psi) - b, all samples weighted by w_i:
    "none"   : A = I, b = 0                      1 unknown  (the seed's basic process)
    "seed7"  : A = diag(s), b (3)                7 unknowns (eq. 9.6: k1 = 1/s, kdb1 = b/s)
    "full12" : A full 3x3 (soft iron), b (3)     13 unknowns (beyond the seed)
The seed writes eq. 9.6 as k1*h = m + kdb1; that is the same family (s = 1/k1, b = kdb1/k1);
we fit the output-error form because there the residual is exactly the sensor noise.

Solver (variable projection + Gauss-Newton, numpy only): for fixed psi the model is linear in
(A, b), solved in closed form (weighted normal equations). The profile cost c(psi) is scanned
on a grid (plus the closed-form 2-D rotation fit of the undistorted model as a candidate), the
best point starts a Gauss-Newton iteration on all unknowns (quadratic convergence; exact on
noiseless data).

Covariance (beyond the seed):
    H = J^T W J,  J = dr/dtheta (3N x p), W = diag(w) (per-sample weight on its 3 rows)
    white part : P_w = s2 * H^-1 J^T W R W J H^-1  (sandwich: W need not be R^-1, because the
                 weights also carry the gyro drift), s2 = max(1, r^T W r / (3N - p)) scales by
                 the residual variance when the data are worse than the noise model says
    consider   : errors c = [gyro errors c_g (K), levelling tilt error beta (2, rad)] common
                 to all samples shift theta by S c, S = -H^-1 J^T W D, D = dr/dc (derived in
                 ``consider_jacobian``); P_theta = P_w + S P_c S^T. The gyro errors act through
                 the attitude error alpha(t) = G(t) c_g of the propagated C_ISF<-SF (G from the
                 estimator: bias columns -int C dt, scale/misalignment columns int C[:, i] w_j dt).

Gate (claim 10, beyond the seed): a solution is withheld with a named reason when there are too
few samples, the field direction in SF has not swept enough angle (orientation diversity), the
column-normalised weighted Jacobian is ill conditioned, the psi sigma is too large or the fit
does not fit (normalised residual).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.rotations import frame_rot_x, frame_rot_y, frame_rot_z, skew, wrap_2pi, wrap_pi

MODELS = ("none", "seed7", "full12")
N_TILT = 2
"""Levelling tilt consider parameters (rad, AF x/y); they follow the K gyro-error ones."""


# --- frames and closed forms ----------------------------------------------------------------

def C_isf_from_af(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """C_ISF<-AF = R1(roll) R2(pitch) (METHODS.md A step 2).

    Derivation: with yaw measured from x_AF the sensor attitude at launch is
    C_AF<-ISF = R_y(pitch) R_x(roll) (ZYX Euler, yaw 0), hence C_ISF<-AF = R_x^T R_y^T = R1 R2.
    """
    return frame_rot_x(roll_rad) @ frame_rot_y(pitch_rad)


def r3(psi_rad: float) -> np.ndarray:
    """R3(psi) = C_AF<-NF."""
    return frame_rot_z(psi_rad)


def dr3_dpsi(psi_rad: float) -> np.ndarray:
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    return np.array([[-s, c, 0.0], [-c, -s, 0.0], [0.0, 0.0, 0.0]])


def psi_from_sample(h_af: np.ndarray, e_ned: np.ndarray) -> float:
    """psi_s from one undistorted field sample in AF (eq. 5.3): delta - atan2(h_y, h_x)."""
    delta = math.atan2(e_ned[1], e_ned[0])
    return wrap_2pi(delta - math.atan2(h_af[1], h_af[0]))


def psi_closed_form(h_af: np.ndarray, e_ned: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Least-squares 2-D rotation fit of many undistorted samples (not an average of angles).

    min_psi sum_i w_i |P h_af_i - P R3(psi) e|^2 (P: horizontal part). Expanding, only
    -2 sum_i w_i h_i^T R3(psi) e depends on psi; with e constant this is maximised when R3(psi) e_h
    points along the weighted mean horizontal sample, hence psi = delta - atan2(sum w h_y, sum w h_x).
    """
    h = np.atleast_2d(np.asarray(h_af, float))
    w = np.ones(len(h)) if weights is None else np.asarray(weights, float)
    sx, sy = float(w @ h[:, 0]), float(w @ h[:, 1])
    return wrap_2pi(math.atan2(e_ned[1], e_ned[0]) - math.atan2(sy, sx))


def azimuth_of(v_ned: np.ndarray) -> float:
    """Azimuth of a NED vector, [0, 2pi) (eq. 8)."""
    return wrap_2pi(math.atan2(v_ned[1], v_ned[0]))


def azimuth_gradient(v_ned: np.ndarray) -> np.ndarray:
    """d azimuth / d v for a NED vector (1/(N^2+E^2) * [-E, N, 0]); inf-free: returns huge values
    when v is vertical, which the sigma then honestly shows."""
    h2 = max(v_ned[0] ** 2 + v_ned[1] ** 2, 1e-300)
    return np.array([-v_ned[1], v_ned[0], 0.0]) / h2


# --- the fit --------------------------------------------------------------------------------

@dataclass(frozen=True)
class FitData:
    """Samples for one solve, stacked. N samples."""
    C_sf_from_isf: np.ndarray
    """(N, 3, 3) gyro-propagated attitude at each sample."""
    h_sf_gauss: np.ndarray
    """(N, 3) measured field, gauss, sensor axes."""
    var_white_gauss2: np.ndarray
    """(N,) per-axis variance of the white part of each residual (mag noise + ARW), G^2."""
    weight: np.ndarray
    """(N,) weight of each sample's 3 residual rows (1/G^2), usually 1/(white + drift variance)."""
    G_gyro: np.ndarray | None = None
    """(N, 3, K) attitude-error sensitivity at each sample: alpha_ISF = G c_g for the K gyro
    error parameters c_g (see module doc). None: K = 0 (tilt-only consider analysis)."""


@dataclass(frozen=True)
class FitResult:
    ok: bool
    """Solver converged to finite numbers (the gate is separate)."""
    model: str
    psi_rad: float
    theta: np.ndarray
    """[psi, linear unknowns...] (see ``unpack``)."""
    A: np.ndarray
    """Distortion matrix (3x3): h = A m + b."""
    b_gauss: np.ndarray
    cov_white: np.ndarray
    """(p, p) white-noise covariance of theta (scaled by s2)."""
    S_consider: np.ndarray
    """(p, K + 2) sensitivity of theta to the consider errors [c_g, beta]."""
    s2: float
    """Normalised residual r^T W r / (3N - p) (1 when the noise model is right)."""
    residual_rms_gauss: float
    condition_number: float
    n_samples: int
    iterations: int
    reason: str = ""
    c_hat: np.ndarray | None = None
    """(K + 2) estimated gyro errors and levelling tilt (zeros when only considered)."""
    P_psi_c: np.ndarray | None = None
    """(1 + K + 2)^2 joint covariance of [psi, c] (white + prior), for the output sigma."""
    psi_sigma_gate_rad: float = math.nan
    """psi sigma without the levelling-tilt share (what the data determine; used by the gate)."""


def n_unknowns(model: str) -> int:
    return {"none": 1, "seed7": 7, "full12": 13}[model]


def unpack(model: str, theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """theta -> (psi, A, b). seed7: [psi, s_x, s_y, s_z, b_x, b_y, b_z]; full12: [psi, A row-major, b]."""
    psi = float(theta[0])
    if model == "none":
        return psi, np.eye(3), np.zeros(3)
    if model == "seed7":
        return psi, np.diag(theta[1:4]), np.asarray(theta[4:7], float)
    return psi, np.asarray(theta[1:10], float).reshape(3, 3), np.asarray(theta[10:13], float)


def seed_k1_kdb1(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The seed's eq. 9.6 unknowns from a diagonal A: k1 = 1/s, kdb1 = b/s."""
    s = np.diag(A)
    return 1.0 / s, b / s


def _field_terms(C_sf_from_af: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """m_i(psi) = cos(psi) U_i + sin(psi) V_i + Z_i (R3(psi) e = [c eN + s eE, -s eN + c eE, eD])."""
    U = C_sf_from_af @ np.array([e[0], e[1], 0.0])
    V = C_sf_from_af @ np.array([e[1], -e[0], 0.0])
    Z = C_sf_from_af @ np.array([0.0, 0.0, e[2]])
    return U, V, Z


def _solve_linear(model: str, m: np.ndarray, h: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted LS for (A, b) given the predicted fields m (N,3): h_i = A m_i + b."""
    if model == "none":
        return np.eye(3), np.zeros(3)
    if model == "seed7":
        s = np.empty(3)
        b = np.empty(3)
        sw, = (w.sum(),)
        for j in range(3):
            x = m[:, j]
            # normal equations of h_j = s_j x + b_j
            N = np.array([[w @ (x * x), w @ x], [w @ x, sw]])
            rhs = np.array([w @ (x * h[:, j]), w @ h[:, j]])
            sol = np.linalg.lstsq(N, rhs, rcond=None)[0]
            s[j], b[j] = sol
        return np.diag(s), b
    X = np.hstack([m, np.ones((len(m), 1))])
    Xw = X * w[:, None]
    beta = np.linalg.lstsq(X.T @ Xw, Xw.T @ h, rcond=None)[0]  # (4, 3)
    return beta[:3].T.copy(), beta[3].copy()


def _profile_costs(model, psis, U, V, Z, h, w):
    """Profile cost c(psi) = min_(A,b) sum_i w_i |h_i - A m_i(psi) - b|^2 for many psi at once
    (the linear unknowns solved in closed form for each psi)."""
    c, sn = np.cos(psis)[:, None, None], np.sin(psis)[:, None, None]
    m = c * U + sn * V + Z                                         # (K, N, 3)
    if model == "none":
        r = h - m
    elif model == "seed7":
        S1 = w.sum()
        Sx = np.einsum("n,knj->kj", w, m)
        Sxx = np.einsum("n,knj->kj", w, m * m)
        Sh = w @ h                                                 # (3,)
        Sxh = np.einsum("n,knj,nj->kj", w, m, h)
        det = Sxx * S1 - Sx * Sx
        ok = det > 1e-12 * np.maximum(Sxx * S1, 1e-300)
        det = np.where(ok, det, 1.0)
        sc = np.where(ok, (S1 * Sxh - Sx * Sh) / det, 0.0)        # 2x2 normal equations per axis
        bb = np.where(ok, (Sxx * Sh - Sx * Sxh) / det, Sh / S1)
        r = h - sc[:, None, :] * m - bb[:, None, :]
        physical = np.all(sc >= 0.0, axis=1)
    else:
        X = np.concatenate([m, np.ones(m.shape[:2] + (1,))], axis=2)  # (K, N, 4)
        Xw = X * w[:, None]
        beta = np.linalg.pinv(np.einsum("kni,knj->kij", Xw, X)) @ np.einsum("kni,nj->kij", Xw, h)
        r = h - X @ beta
        physical = np.linalg.det(beta[:, :3, :]) > -1e-9
    cost = np.einsum("n,kni,kni->k", w, r, r)
    if model != "none":
        # near the magnetic equator (e_D ~ 0) m(psi + pi) ~ -m(psi): A -> -A fits as well; only
        # distortion matrices that keep the field's handedness (det A > 0, scales > 0) are physical;
        # when none is (degenerate data) the plain minimum is kept and the gate will say why
        if np.any(physical):
            cost = np.where(physical, cost, np.inf)
    return cost


def _residual_and_jacobian(model, theta, Cfa, e, h):
    """r = h - A m(psi) - b stacked sample-major (3N,), J = dr/dtheta (3N, p)."""
    psi, A, b = unpack(model, theta)
    R = r3(psi)
    m = Cfa @ (R @ e)                                   # (N,3)
    dm = Cfa @ (dr3_dpsi(psi) @ e)                      # (N,3) dm/dpsi
    r = h - m @ A.T - b
    N = len(h)
    p = n_unknowns(model)
    J = np.zeros((N, 3, p))
    J[:, :, 0] = -dm @ A.T
    if model == "seed7":
        for j in range(3):
            J[:, j, 1 + j] = -m[:, j]
            J[:, j, 4 + j] = -1.0
    elif model == "full12":
        for j in range(3):
            J[:, j, 1 + 3 * j:4 + 3 * j] = -m
            J[:, j, 10 + j] = -1.0
    return r.reshape(-1), J.reshape(3 * N, p), m


def consider_jacobian(model: str, theta: np.ndarray, C_sf_from_isf: np.ndarray, C_isf_af: np.ndarray,
                      e: np.ndarray, G_gyro: np.ndarray | None) -> np.ndarray:
    """D = dr/dc (3N, K + 2) for c = [gyro errors c_g (K), levelling tilt beta (2)].

    Gyro: the propagated C^_ISF<-SF = (I + [alpha]x) C_ISF<-SF. With a rate error eps (estimated
    minus true rate, sensor axes), d/dt of that gives [alpha']x = C [eps]x C^T, alpha' = C eps:
    a bias error db gives alpha = -int C dt db, a scale/misalignment matrix T (w_meas = (I+T) w)
    alpha = sum_ij T_ij int C[:, i] w_j dt; both are alpha = G c_g. Then
    m^ = C^_SF<-ISF e_ISF = m + C_SF<-ISF [e_ISF]x alpha and dr/dc_g = -A C_SF<-ISF [e_ISF]x G.
    Levelling: C^_AF<-ISF = (I + [beta]x) C_AF<-ISF (beta in AF, only x/y matter: z is psi), so
    m^ = m + C_SF<-AF [e_AF]x beta and dr/d beta = -A C_SF<-AF [e_AF]x[:, :2].
    """
    psi, A, _ = unpack(model, theta)
    e_af = r3(psi) @ e
    e_isf = C_isf_af @ e_af
    N = len(C_sf_from_isf)
    K = 0 if G_gyro is None else G_gyro.shape[2]
    D = np.zeros((N, 3, K + N_TILT))
    if K:
        D[:, :, :K] = -(A @ (C_sf_from_isf @ skew(e_isf))) @ G_gyro
    Cfa = C_sf_from_isf @ C_isf_af
    D[:, :, K:] = -(A @ (Cfa @ skew(e_af)))[:, :, :2]
    return D.reshape(3 * N, K + N_TILT)


def _finite_samples(data: FitData) -> np.ndarray:
    """(N,) whether each sample's field, attitude, variance, weight and G are all finite."""
    ok = (np.all(np.isfinite(np.asarray(data.h_sf_gauss, float)), axis=1)
          & np.all(np.isfinite(np.asarray(data.C_sf_from_isf, float)), axis=(1, 2))
          & np.isfinite(np.asarray(data.var_white_gauss2, float)) & np.isfinite(np.asarray(data.weight, float)))
    if data.G_gyro is not None:
        ok &= np.all(np.isfinite(np.asarray(data.G_gyro, float)), axis=(1, 2))
    return ok


def fit_psi(data: FitData, C_isf_af: np.ndarray, e_ned: np.ndarray, model: str = "seed7",
            grid_points: int = 36, max_iterations: int = 20, tol_rad: float = 1e-12,
            P_prior: np.ndarray | None = None, estimate_errors: bool = False) -> FitResult:
    """Solve for psi_s (and the distortion unknowns of ``model``) from the samples in ``data``.

    ``P_prior`` ((K+2)^2): prior covariance of the gyro errors and the levelling tilt. With
    ``estimate_errors`` False they are consider parameters (their effect enters the covariance
    only); with True they are estimated jointly (MAP with the prior, see ``_estimate_errors``).
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    e = np.asarray(e_ned, float)
    h = np.asarray(data.h_sf_gauss, float)
    w = np.asarray(data.weight, float)
    N = len(h)
    p = n_unknowns(model)
    K = 0 if data.G_gyro is None else data.G_gyro.shape[2]
    nan_res = FitResult(False, model, math.nan, np.full(p, math.nan), np.eye(3), np.zeros(3),
                        np.full((p, p), math.nan), np.zeros((p, K + N_TILT)), math.nan, math.nan,
                        math.inf, N, 0)
    if 3 * N <= p:
        return _replace_reason(nan_res, f"{N} samples give {3 * N} equations for {p} unknowns")
    n_bad = N - int(np.count_nonzero(_finite_samples(data)))
    if n_bad:   # a named reason, not a LinAlgError from deep inside the solve
        return _replace_reason(nan_res, f"{n_bad} of {N} samples not finite")
    Cfa = data.C_sf_from_isf @ C_isf_af                               # (N,3,3) C_SF<-AF
    U, V, Z = _field_terms(Cfa, e)
    # candidates: closed-form 2-D fit of the undistorted model, and a grid over [0, 2pi)
    h_af = np.einsum("nji,nj->ni", Cfa, h)                            # C_AF<-SF h
    cands = np.concatenate([[psi_closed_form(h_af, e, w)], np.linspace(0.0, 2 * math.pi, grid_points, endpoint=False)])
    costs = _profile_costs(model, cands, U, V, Z, h, w)
    psi0 = float(cands[int(np.argmin(costs))])
    m0 = math.cos(psi0) * U + math.sin(psi0) * V + Z
    A0, b0 = _solve_linear(model, m0, h, w)
    theta = _pack(model, psi0, A0, b0)
    sw = np.repeat(w, 3)
    r, J, _ = _residual_and_jacobian(model, theta, Cfa, e, h)
    cost = float(sw @ (r * r))
    it = 0
    for it in range(1, max_iterations + 1):
        Jw = J * sw[:, None]
        step = -(_inv_spd(J.T @ Jw) @ (Jw.T @ r))                 # Gauss-Newton normal equations
        lam = 1.0
        while True:  # step halving keeps the cost non-increasing
            th_new = theta + lam * step
            r_new, J_new, _ = _residual_and_jacobian(model, th_new, Cfa, e, h)
            c_new = float(sw @ (r_new * r_new))
            if c_new <= cost * (1 + 1e-12) + 1e-300 or lam < 1e-4:
                break
            lam *= 0.5
        theta, r, J, cost = th_new, r_new, J_new, c_new
        if abs(lam * step[0]) < tol_rad:
            break
    theta[0] = wrap_2pi(theta[0])
    if not np.all(np.isfinite(theta)):
        return _replace_reason(nan_res, "least squares did not converge")
    r, J, m = _residual_and_jacobian(model, theta, Cfa, e, h)
    Jw = J * sw[:, None]
    H = J.T @ Jw
    H_inv = _inv_spd(H)
    dof = 3 * N - p
    s2_raw = float(sw @ (r * r)) / dof
    R_white = np.repeat(data.var_white_gauss2, 3)
    P_w = H_inv @ (Jw.T @ (Jw * R_white[:, None])) @ H_inv * max(1.0, s2_raw)
    D = consider_jacobian(model, theta, data.C_sf_from_isf, C_isf_af, e, data.G_gyro)
    S = -H_inv @ (Jw.T @ D)
    # conditioning of the weighted Jacobian with unit-norm columns: sqrt(cond) of the scaled H
    dn = np.sqrt(np.diag(H))
    dn = np.where(dn > 0, dn, 1.0)
    ev = np.linalg.eigvalsh(H / np.outer(dn, dn))
    cond = float(math.sqrt(ev[-1] / ev[0])) if ev[0] > ev[-1] * 1e-30 else math.inf
    Kc = D.shape[1]
    P_c = np.zeros((Kc, Kc)) if P_prior is None else np.asarray(P_prior, float)
    if P_c.shape != (Kc, Kc):
        raise ValueError(f"P_prior must be {Kc}x{Kc}, got {P_c.shape}")
    if estimate_errors and np.any(np.diag(P_c) > 0):
        return _estimate_errors(model, theta, Cfa, e, h, data.var_white_gauss2, D, P_c, P_w, S, s2_raw,
                                cond, N, it)
    s0 = S[0]
    P_psi_c = np.empty((1 + Kc, 1 + Kc))
    P_psi_c[0, 0] = P_w[0, 0] + s0 @ P_c @ s0
    P_psi_c[0, 1:] = P_psi_c[1:, 0] = s0 @ P_c
    P_psi_c[1:, 1:] = P_c
    s_nt = s0.copy()
    s_nt[-N_TILT:] = 0.0
    psi, A, b = unpack(model, theta)
    return FitResult(True, model, psi, theta, A, b, P_w, S, s2_raw,
                     float(math.sqrt(float(r @ r) / (3 * N))), cond, N, it,
                     c_hat=np.zeros(Kc), P_psi_c=P_psi_c,
                     psi_sigma_gate_rad=math.sqrt(max(P_w[0, 0] + s_nt @ P_c @ s_nt, 0.0)))


def _estimate_errors(model, theta, Cfa, e, h, var_white, D, P_c, P_w, S, s2_raw, cond, N, it,
                     iterations: int = 3) -> FitResult:
    """Joint MAP of [theta, c] with the prior c ~ N(0, P_c) (c with zero prior variance stay 0).

    The propagated attitude carries the errors c_true, so the residual at c = 0 is r(theta) =
    D c_true (D from ``consider_jacobian``); correcting by an estimate c leaves
    r(theta, c) ~ r(theta) - D c (first order in the small c). Data weights 1/var_white (the drift
    is now modelled, not inflated):
        minimise  r^T W r + c^T P_c^-1 c
    by Gauss-Newton on [theta, c], J_a = [J, -D]; posterior covariance
    (J_a^T W J_a + diag(0, P_c^-1))^-1, scaled by max(1, normalised residual). The returned
    P_psi_c is the covariance of (psi error, c_true - c_hat), the attitude error left after the
    correction, so the output sigma uses the same v = [1, k] as in the consider case. The unobservable direction (a rotation about the field
    vector mixes psi and tilt) is held by the tilt prior, so psi's sigma keeps that share.
    """
    p = len(theta)
    free = np.flatnonzero(np.diag(P_c) > 0)
    info = 1.0 / np.diag(P_c)[free]
    Df = -D[:, free]                      # d r / d c_hat
    Ww = np.repeat(1.0 / var_white, 3)
    c = np.zeros(len(free))

    def normal_eqs(th, c_, prior_info):
        r_, J_, _ = _residual_and_jacobian(model, th, Cfa, e, h)
        r_lin = r_ + Df @ c_
        Ja = np.hstack([J_, Df])
        JaW = Ja * Ww[:, None]
        H = Ja.T @ JaW
        H[p:, p:] += np.diag(prior_info)
        g = JaW.T @ r_lin
        g[p:] += prior_info * c_
        return H, g, r_lin

    for _ in range(iterations):
        H, g, _ = normal_eqs(theta, c, info)
        step = -(_inv_spd(H) @ g)
        theta = theta + step[:p]
        c = c + step[p:]
    H, _, r_lin = normal_eqs(theta, c, info)
    dof = max(len(r_lin) - p, 1)
    s2 = float(Ww @ (r_lin * r_lin)) / dof
    scale = max(1.0, s2)
    Hinv = _inv_spd(H) * scale
    Kc = D.shape[1]
    idx = np.concatenate([[0], p + np.arange(len(free))])
    P_psi_c = np.zeros((1 + Kc, 1 + Kc))
    sel = np.concatenate([[0], 1 + free])
    P_psi_c[np.ix_(sel, sel)] = Hinv[np.ix_(idx, idx)]
    P_psi_c[0, 1:] *= -1.0                # cov(psi err, c_hat - c) -> cov(psi err, c - c_hat)
    P_psi_c[1:, 0] *= -1.0
    # gate: the same posterior with the tilt held fixed (its share does not shrink with data)
    info_nt = info.copy()
    info_nt[free >= Kc - N_TILT] = 1e16
    H_nt, _, _ = normal_eqs(theta, c, info_nt)
    psi_var_nt = float(_inv_spd(H_nt)[0, 0]) * scale
    c_full = np.zeros(Kc)
    c_full[free] = c
    theta[0] = wrap_2pi(theta[0])
    psi, A, b = unpack(model, theta)
    return FitResult(True, model, psi, theta, A, b, P_w, S, s2,
                     float(math.sqrt(float(r_lin @ r_lin) / len(r_lin))), cond, N, it,
                     c_hat=c_full, P_psi_c=P_psi_c, psi_sigma_gate_rad=math.sqrt(max(psi_var_nt, 0.0)))


def _inv_spd(H: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi)definite matrix with Jacobi scaling (the unknowns
    span gauss, radians, scale factors and rad/s: scaling keeps the pseudo-inverse accurate)."""
    d = np.sqrt(np.abs(np.diag(H)))
    d = np.where(d > 0, d, 1.0)
    Hs = H / np.outer(d, d)
    Hs = 0.5 * (Hs + Hs.T)
    try:
        inv = np.linalg.inv(Hs)
        if np.all(np.isfinite(inv)) and np.linalg.cond(Hs) < 1e13:
            return inv / np.outer(d, d)
    except np.linalg.LinAlgError:
        pass
    return np.linalg.pinv(Hs, rcond=1e-13, hermitian=True) / np.outer(d, d)   # singular: unobservable


def _pack(model, psi, A, b):
    if model == "none":
        return np.array([psi])
    if model == "seed7":
        return np.concatenate([[psi], np.diag(A), b])
    return np.concatenate([[psi], A.reshape(-1), b])


def _replace_reason(res: FitResult, reason: str) -> FitResult:
    from dataclasses import replace
    return replace(res, reason=reason)


def psi_variance(fit: FitResult, P_consider: np.ndarray, include_tilt: bool = True) -> float:
    """Variance of psi_s: white part plus the consider errors' share (the levelling-tilt part
    only when ``include_tilt``: it does not shrink with more data, so the gate leaves it out)."""
    s = fit.S_consider[0].copy()
    if not include_tilt:
        s[-N_TILT:] = 0.0
    return float(fit.cov_white[0, 0] + s @ P_consider @ s)


def orientation_diversity_rad(C_sf_from_af: np.ndarray, psi_rad: float, e_ned: np.ndarray) -> float:
    """Largest angle between the predicted Earth-field directions in SF over the samples.

    Uses m_i = C_SF<-AF R3(psi) e (gyro attitude, not the distorted measurement): 0 when the
    sensor has not turned relative to the field, whatever the hard iron.
    """
    m = C_sf_from_af @ (r3(psi_rad) @ np.asarray(e_ned, float))
    u = m / np.linalg.norm(m, axis=1)[:, None]
    # the smallest cosine, then clipped (the same number as clipping all N^2 first: clip is monotonic)
    return float(math.acos(min(1.0, max(-1.0, float(np.min(u @ u.T))))))


# --- the gate -------------------------------------------------------------------------------

@dataclass(frozen=True)
class GateParams:
    min_samples: int = 30
    """Fewest samples in a fit (3 s at the default 10 Hz decimation)."""
    min_diversity_rad: float = math.radians(20.0)
    """Smallest angle the field direction must have swept in the sensor frame."""
    max_condition_number: float = 1.0e4
    """Largest condition number of the weighted, column-normalised Jacobian."""
    max_psi_sigma_rad: float = math.radians(1.0)
    """Largest accepted 1-sigma of psi_s as the data determine it (without the levelling-tilt
    share, which no amount of data reduces); early solutions above it were found to be biased."""
    max_normalised_residual: float = 25.0
    """Largest r^T W r / dof: above it the distortion model does not describe the data."""

    def __post_init__(self):
        if self.min_samples < 1:
            raise ValueError(f"min_samples must be >= 1, got {self.min_samples}")
        if not 0.0 <= self.min_diversity_rad < math.pi:
            raise ValueError(f"min_diversity_rad must be in [0, pi), got {self.min_diversity_rad}")
        for name in ("max_condition_number", "max_psi_sigma_rad", "max_normalised_residual"):
            v = getattr(self, name)
            if not v > 0.0:
                raise ValueError(f"{name} must be > 0, got {v}")


def gate_reason(fit: FitResult | None, n_samples: int, diversity_rad: float, psi_sigma_rad: float,
                params: GateParams) -> str:
    """'' when the solution may be published, else the first failed condition, named."""
    if n_samples < params.min_samples:
        return f"{n_samples} magnetometer samples < {params.min_samples} required"
    if diversity_rad < params.min_diversity_rad:
        return (f"orientation diversity {math.degrees(diversity_rad):.1f} deg < "
                f"{math.degrees(params.min_diversity_rad):.0f} deg required")
    if fit is None or not fit.ok:
        return "fit failed: " + (fit.reason if fit is not None else "not run")
    if fit.condition_number > params.max_condition_number:
        return (f"Jacobian condition number {fit.condition_number:.3g} > "
                f"{params.max_condition_number:.3g} (unknowns not observable yet)")
    if not np.linalg.det(fit.A) > 0.0:
        return "distortion solution not physical (det A <= 0)"
    if fit.s2 > params.max_normalised_residual:
        return (f"normalised residual {fit.s2:.1f} > {params.max_normalised_residual:.1f} "
                f"(residual RMS {fit.residual_rms_gauss * 1e3:.1f} mG: model does not fit)")
    if not psi_sigma_rad <= params.max_psi_sigma_rad:
        return (f"psi_s sigma {math.degrees(psi_sigma_rad):.2f} deg > "
                f"{math.degrees(params.max_psi_sigma_rad):.2f} deg")
    return ""


# --- output: azimuth of a sensor-fixed direction and its sigma ------------------------------

def direction_azimuth_and_sigma(u_sf: np.ndarray, C_nf_af: np.ndarray, C_af_isf: np.ndarray,
                                C_isf_sf: np.ndarray, G_now: np.ndarray, P_psi_c: np.ndarray,
                                arw_var_rad2: float, du_dbeta_sf: np.ndarray | None = None) -> tuple[float, float, np.ndarray]:
    """Azimuth (eq. 6-8) of the sensor-fixed direction u_sf now, with its 1-sigma.

    u_NF = R3(psi)^T C_AF<-ISF C_ISF<-SF(t) u_SF (the matrices as corrected by any estimated
    errors). Errors, to first order (g = d az / d u_NF):
      psi error           : d az = d psi                       (a rotation about down)
      gyro errors c_g     : d u_NF = -C_NF<-ISF [u_ISF]x G(t) c_g  (alpha = G c_g, du = alpha x u)
      levelling tilt beta : d u_NF = -R3(psi)^T [u_AF]x beta
      ARW (white)         : var = |g C_NF<-ISF [u_ISF]x|^2 * arw_var (isotropic per axis)
      u from gravity      : d u_NF = C_NF<-SF du_dbeta beta  (vertical launcher: u_SF is the
                            measured up, which carries the same tilt error as the levelling)
    psi and c are correlated (the fit trades them), so with v = [1, k], k = d az / d c now:
        var = v^T P_[psi,c] v + ARW.
    Returns (azimuth, sigma, u_NF).
    """
    u_isf = C_isf_sf @ u_sf
    u_af = C_af_isf @ u_isf
    u_nf = C_nf_af @ u_af
    g = azimuth_gradient(u_nf)
    gC = g @ C_nf_af
    L = np.cross(gC @ C_af_isf, u_isf)           # = g C_NF<-ISF [u_ISF]x  (a^T [u]x = (a x u)^T)
    K = G_now.shape[1]
    v = np.empty(1 + K + N_TILT)
    v[0] = 1.0
    v[1:1 + K] = -(L @ G_now)
    v[1 + K:] = -np.cross(gC, u_af)[:2]
    if du_dbeta_sf is not None:
        v[1 + K:] += (gC @ C_af_isf @ C_isf_sf) @ du_dbeta_sf
    var = v @ P_psi_c @ v + float(L @ L) * arw_var_rad2
    return azimuth_of(u_nf), math.sqrt(max(var, 0.0)), u_nf


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors (rad), robust near 0 and pi."""
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), float(a @ b))


__all__ = [
    "MODELS", "C_isf_from_af", "r3", "psi_from_sample", "psi_closed_form", "azimuth_of",
    "FitData", "FitResult", "fit_psi", "unpack", "seed_k1_kdb1", "consider_jacobian",
    "psi_variance", "orientation_diversity_rad", "GateParams", "gate_reason",
    "direction_azimuth_and_sigma", "angle_between", "wrap_pi",
]
