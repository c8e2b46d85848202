// Method C's heading filter: the compiled twin of estimators/polar_heading.py, which stays the
// reference and holds the derivation (the Euler formulation, 4 states [psi, w_v, b_y, b_z]; the
// platform formulation, 5 states [psi_H, w_v, b_x, b_y, b_z] with the filter's own body attitude
// C_HB; the magnetometer heading with its white and correlated variance, the innovation gate, the
// reset after continuous rejection, the consider floor and the uncalibrated-magnetometer term of the
// published variance, widened by the field mismatch against the model; unseen intervals). Every scalar expression is the reference's, in its order.
// The n x n products (n = 4 or 5) are dense, as numpy's: a NaN spreads as it does there (no
// structural zero skipped); numpy's BLAS may sum or fuse in its own order, so the two agree to
// rounding: tests/test_core_polar_heading.py asserts 1e-9 relative (covariances against
// sqrt(P_ii P_jj)). A step works on a copy of the state and hands it back only where the reference
// returns a new state (a refused input or a ValueError leaves the held state as it was).
#pragma once

#include <cmath>

#include "ahrs_math.hpp"
#include "polar_attitude.hpp"  // cross3, dot3, sub3 (one helper set)

namespace azimuthd {
namespace polar_heading {

using polar::cross3;
using polar::dot3;

constexpr int NM = 5;                 // storage: the platform formulation's 5 states
using XH = std::array<double, NM>;
using PH = Mat<NM, NM>;                // row-major, stride NM; the Euler formulation uses the top-left 4 x 4
constexpr double WITHHELD_AFTER_S = 1.0;  // estimators.polar_heading.WITHHELD_AFTER_S

// estimators.polar_heading.PolarHeadingParams
struct Params {
    double gyro_noise_rad_s_rt_hz, gyro_bias_sigma_rad_s, gyro_bias_tau_s, vertical_rate_sigma_rad_s,
        vertical_rate_tau_s, attitude_error_tau_s, heading_process_floor_rad_s_rt_hz, mag_noise_gauss,
        mag_heading_floor_rad, min_horizontal_field_gauss, mag_update_period_s, mag_error_tau_s, mag_error_turn_rad,
        consider_floor_fraction, uncalibrated_hard_iron_gauss, uncalibrated_soft_iron, gate_chi2, reset_after_s,
        max_abs_pitch_rad, max_dt_s, unseen_rate_sigma_rad_s, unseen_max_sigma_rad;
};

// estimators.polar_heading.PolarHeadingState (has_*: the reference's Optional fields)
struct State {
    bool initialised = false;
    bool has_time = false;
    double time_s = 0.0;
    int n = 4;        // len(x)
    XH x{};
    PH P{};
    bool has_last_mag = false;
    double last_mag_time_s = 0.0;
    bool source_available = false;
    bool has_rejected_since = false;
    double rejected_since_s = 0.0;
    long n_fused = 0, n_rejected = 0, n_resets = 0;
    bool has_r_corr_avg = false;
    double r_corr_avg_rad2 = 0.0;
    double r_uncal_rad2 = 0.0;
    bool has_field_mismatch = false;       // field_mismatch_gauss2 not None
    double field_mismatch_gauss2 = 0.0;
    bool has_field_mismatch_time = false;  // field_mismatch_time_s not None
    double field_mismatch_time_s = 0.0;
    bool platform = false;
    bool has_q = false;
    Q4 q_P_from_body{1.0, 0.0, 0.0, 0.0};
    bool has_gyro_bias_prev = false;  // unused by the filter (kept so saved states load)
    V3 gyro_bias_prev_rad_s{};
};

// estimators.polar_heading.HeadingInputs, read once by the binding
struct Inputs {
    double time_s;
    V3 gyro;
    double roll, pitch;
    Mat<2, 2> cov_rp;
    bool has_mag;
    V3 mag;
    double declination, declination_sigma;
    bool has_residual;
    double residual_sigma;
    bool has_field_model;  // field_model_ned_gauss not None
    V3 field_model;
    bool has_q;
    Q4 q_P;
    bool has_cov_att;
    M3 cov_att;
    bool level_with_roll_pitch;
};

// what a step did: the reference's HeadingDiag (reason worded by the Python face)
enum Code : int {
    PLAIN = 0,               // HeadingDiag(source_available=...)
    NON_FINITE_INPUT = 1,    // "non-finite input"
    TIME_NOT_INCREASING = 2, // "time not increasing (dt=%.6f s)" (source_available False)
    NON_FINITE_MAG = 3,      // "non-finite magnetometer"
    PITCH_BEYOND = 4,        // "pitch beyond max_abs_pitch_rad"
    FIELD_WEAK = 5,          // "horizontal field %.4f G < %s G" (measured False, source_available False)
    MEASURED = 6,            // a heading measurement (why below)
    BAD_DECLINATION = 7,     // the reference raises ValueError (state not handed back)
    BAD_RESIDUAL = 8,        // the reference raises ValueError (the Python face words it)
    BAD_FIELD_MODEL = 9,     // the reference raises ValueError (the Python face words it)
};
enum Why : int { FUSED = 0, INITIALISED = 1, RESET = 2, GATED_OUT = 3 };

struct Diag {
    int code = PLAIN;
    bool source_available = false;
    double dt_s = 0.0;
    double H = NAN, z = NAN, nu = NAN, S = NAN, ratio = NAN, reset_jump = 0.0;
    int why = FUSED;
};

// --- small pieces ---------------------------------------------------------------------------------

inline void gm(double dt, double tau, double sigma, double& a, double& q) {
    a = std::exp(-dt / tau);
    q = sigma * sigma * (1.0 - a * a);
}

// _prior_P(var_psi, p, n)
inline PH prior_P(double var_psi, const Params& p, int n) {
    PH P{};
    P[0] = var_psi;
    P[1 * NM + 1] = std::pow(p.vertical_rate_sigma_rad_s, 2);
    for (int i = 2; i < n; ++i) P[i * NM + i] = std::pow(p.gyro_bias_sigma_rad_s, 2);
    return P;
}

// F @ P @ F.T, dense (numpy's (F @ P) @ F.T)
inline PH fpft(const PH& F, const PH& P, int n) {
    PH A{}, B{};
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) {
            double s = F[i * NM] * P[j];
            for (int k = 1; k < n; ++k) s = s + F[i * NM + k] * P[k * NM + j];
            A[i * NM + j] = s;
        }
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) {
            double s = A[i * NM] * F[j * NM];
            for (int k = 1; k < n; ++k) s = s + A[i * NM + k] * F[j * NM + k];
            B[i * NM + j] = s;
        }
    return B;
}

// float(v @ A @ v) for a 2-vector and a 2 x 2 A: (v @ A) @ v
inline double quad2(double v0, double v1, const Mat<2, 2>& A) {
    const double a0 = v0 * A[0] + v1 * A[2];
    const double a1 = v0 * A[1] + v1 * A[3];
    return a0 * v0 + a1 * v1;
}

// magnetic_heading: (magnetic heading in [0, 2pi), horizontal field) of a levelled magnetometer
inline void magnetic_heading(const V3& m, double roll, double pitch, double& psi, double& H) {
    const double cr = std::cos(roll), sr = std::sin(roll);
    const double cp = std::cos(pitch), sp = std::sin(pitch);
    const double my = cr * m[1] - sr * m[2];
    const double mz1 = sr * m[1] + cr * m[2];
    const double mx = cp * m[0] + sp * mz1;
    psi = wrap_2pi(std::atan2(-my, mx));
    H = std::hypot(mx, my);
}

// uncalibrated_heading_var (a residual sigma checked by the caller: BAD_RESIDUAL before this)
inline double uncalibrated_heading_var(const V3& m, double H, bool has_residual, double residual, const Params& p) {
    const double H2 = H * H;
    if (!has_residual) {
        const double m2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2];
        return (std::pow(p.uncalibrated_hard_iron_gauss, 2) + std::pow(p.uncalibrated_soft_iron, 2) * m2) / H2;
    }
    return std::max(0.0, std::pow(residual, 2) - std::pow(p.mag_noise_gauss, 2)) / H2;
}

inline bool residual_ok(const Inputs& u) {
    return !u.has_residual || (std::isfinite(u.residual_sigma) && u.residual_sigma >= 0.0);
}

inline bool field_model_ok(const Inputs& u) {
    return !u.has_field_model ||
           (finite3(u.field_model) && std::hypot(u.field_model[0], u.field_model[1], u.field_model[2]) > 0.0);
}

// _levelled_down: the down component of R_y(theta) R_x(phi) m
inline double levelled_down(const V3& m, double roll, double pitch) {
    const double mz1 = std::sin(roll) * m[1] + std::cos(roll) * m[2];
    return -std::sin(pitch) * m[0] + std::cos(pitch) * mz1;
}

// field_mismatch_var (the model given, finite, not 0: field_model_ok before this): the field error's
// component normal to the model's field in the magnetic meridian, squared
inline double field_mismatch_var(double H, double Z, const V3& e) {
    const double H0 = std::hypot(e[0], e[1]);
    const double dn = (H * e[2] - Z * H0) / std::hypot(H0, e[2]);
    return dn * dn;
}

// _consider: the running mean of the field mismatch and the consider term of a measurement that enters
// the heading (restart: initialised or reset on it); has_mis false: no model (the mean forgotten)
inline double consider(State& st, double t, double H, double r_uncal, bool has_mis, double mis, const Params& p,
                       bool restart) {
    if (!has_mis) {
        st.has_field_mismatch = false;
        st.field_mismatch_gauss2 = 0.0;
        st.has_field_mismatch_time = false;
        st.field_mismatch_time_s = 0.0;
        return r_uncal;
    }
    double avg;
    if (restart || !st.has_field_mismatch || !st.has_field_mismatch_time)
        avg = mis;
    else
        avg = st.field_mismatch_gauss2 + (mis - st.field_mismatch_gauss2) *
                  std::min(1.0, std::min(std::max(0.0, t - st.field_mismatch_time_s), p.mag_update_period_s) /
                                    p.mag_error_tau_s);   // a gap is not measured time (the reference)
    st.has_field_mismatch = true;
    st.field_mismatch_gauss2 = avg;
    st.has_field_mismatch_time = true;
    st.field_mismatch_time_s = t;
    return std::max(r_uncal, std::max(0.0, avg - std::pow(p.mag_noise_gauss, 2)) / (H * H));
}

// --- init, unseen, estimate, attitude --------------------------------------------------------------

// polar_heading_init (arguments checked by the caller)
inline State init(bool has_heading, double heading, double sigma, bool has_bias, double by, double bz,
                  const Params& p) {
    State s;
    if (has_bias) { s.x[2] = by; s.x[3] = bz; }
    if (!has_heading) return s;
    s.x[0] = wrap_2pi(heading);
    s.initialised = true;
    s.P = prior_P(std::pow(sigma, 2), p, 4);
    return s;
}

// polar_heading_unseen (unseen_s checked finite and >= 0 by the caller)
inline void unseen(State& s, double unseen_s, const Params& p) {
    if (!s.initialised) return;
    double a_v, q_v, a_b, q_b;
    gm(unseen_s, p.vertical_rate_tau_s, p.vertical_rate_sigma_rad_s, a_v, q_v);
    gm(unseen_s, p.gyro_bias_tau_s, p.gyro_bias_sigma_rad_s, a_b, q_b);
    const int n = s.n;
    double f[NM], d[NM];
    f[0] = 1.0; f[1] = a_v; d[0] = 0.0; d[1] = q_v;
    for (int i = 2; i < n; ++i) { f[i] = a_b; d[i] = q_b; }
    PH P{};
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) P[i * NM + j] = f[i] * s.P[i * NM + j] * f[j] + (i == j ? d[i] : 0.0);
    const double sg = std::min(p.unseen_rate_sigma_rad_s * unseen_s, p.unseen_max_sigma_rad);
    P[0] += sg * sg;
    s.x[1] *= a_v;
    s.P = P;
    s.has_time = false;
    s.has_last_mag = false;
    s.has_field_mismatch_time = false;
    s.field_mismatch_time_s = 0.0;
}

// yaw of C_PB
inline double yaw_of(const Q4& q) { return euler_from_dcm(dcm_from_quat(q))[2]; }

// polar_heading_estimate (for an initialised state): heading and its published variance
inline void estimate(const State& s, double& heading, double& var) {
    var = s.P[0];
    heading = s.x[0];
    if (s.platform && s.has_q) heading = wrap_2pi(heading + yaw_of(s.q_P_from_body));
    if (s.has_r_corr_avg) var = std::max(var, s.r_corr_avg_rad2);
    var += s.r_uncal_rad2;
}

// polar_heading_attitude (platform, initialised, q held): R_z(heading - yaw(C_HB)) C_HB
inline Q4 attitude(const State& s, double heading) {
    const double yaw_H = yaw_of(s.q_P_from_body);
    return quat_normalize(quat_mul(quat_from_euler(0.0, 0.0, heading - yaw_H), s.q_P_from_body));
}

// --- the measurement ----------------------------------------------------------------------------------

// _fuse_heading: initialise from, gate, fuse (or reset on) one heading measurement z of x[0]; r_uncal
// becomes the state's consider term only where the measurement enters the heading (not when gated out)
inline Diag fuse_heading(State& st, const Inputs& u, double z, double H, double R, double R_single, double r_corr,
                         double r_uncal, bool has_mis, double mis, const Params& p) {
    Diag dg;
    dg.code = MEASURED;
    dg.source_available = true;
    dg.H = H;
    dg.z = z;
    const int n = st.n;
    if (!st.initialised) {
        st.x[0] = z;
        st.x[1] = 0.0;
        st.initialised = true;
        st.P = prior_P(R_single, p, n);
        st.source_available = true;
        st.r_uncal_rad2 = consider(st, u.time_s, H, r_uncal, has_mis, mis, p, true);
        dg.nu = 0.0;
        dg.S = R_single;
        dg.ratio = 0.0;
        dg.why = INITIALISED;
        return dg;
    }
    const double nu = wrap_pi(z - st.x[0]);
    const double S = st.P[0] + R;
    const double ratio = nu * nu / (st.P[0] + R_single) / p.gate_chi2;
    dg.nu = nu;
    dg.S = S;
    dg.ratio = ratio;
    if (ratio > 1.0) {
        const double since = st.has_rejected_since ? st.rejected_since_s : u.time_s;
        if (u.time_s - since >= p.reset_after_s) {
            for (int i = 0; i < n; ++i) { st.P[i] = 0.0; st.P[i * NM] = 0.0; }
            st.P[0] = R_single;
            st.x[0] = z;
            st.has_rejected_since = false;
            st.source_available = true;
            st.n_resets += 1;
            st.r_uncal_rad2 = consider(st, u.time_s, H, r_uncal, has_mis, mis, p, true);
            dg.why = RESET;
            dg.reset_jump = nu;
            return dg;
        }
        st.has_rejected_since = true;
        st.rejected_since_s = since;
        st.source_available = true;
        st.n_rejected += 1;
        dg.why = GATED_OUT;
        return dg;
    }
    double K[NM];
    for (int i = 0; i < n; ++i) K[i] = st.P[i * NM] / S;
    XH x = st.x;
    for (int i = 0; i < n; ++i) x[i] = st.x[i] + K[i] * nu;
    x[0] = wrap_2pi(x[0]);
    PH I_KH{};
    for (int i = 0; i < n; ++i) {
        I_KH[i * NM + i] = 1.0;
        I_KH[i * NM] -= K[i];
    }
    PH P = fpft(I_KH, st.P, n);
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) P[i * NM + j] = P[i * NM + j] + K[i] * K[j] * R;
    const double dt_m = p.mag_update_period_s;
    const double rc = p.consider_floor_fraction * r_corr;
    const double avg = !st.has_r_corr_avg ? rc
        : st.r_corr_avg_rad2 + (rc - st.r_corr_avg_rad2) * std::min(1.0, dt_m / p.mag_error_tau_s);
    PH Ps{};
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) Ps[i * NM + j] = 0.5 * (P[i * NM + j] + P[j * NM + i]);
    st.x = x;
    st.P = Ps;
    st.has_rejected_since = false;
    st.source_available = true;
    st.n_fused += 1;
    st.has_r_corr_avg = true;
    st.r_corr_avg_rad2 = avg;
    st.r_uncal_rad2 = consider(st, u.time_s, H, r_uncal, has_mis, mis, p, false);
    return dg;
}

// _mag_sample: false with the diag of a refused sample; the declination checked (BAD_DECLINATION)
inline bool mag_sample(State& st, const Inputs& u, Diag& bad) {
    if (!finite3(u.mag)) {
        bad.code = NON_FINITE_MAG;
        bad.source_available = st.source_available;
        return false;
    }
    if (!std::isfinite(u.declination)) {
        bad.code = BAD_DECLINATION;
        return false;
    }
    st.has_last_mag = true;
    st.last_mag_time_s = u.time_s;
    return true;
}

inline Diag field_weak(State& st, double H) {
    st.source_available = false;
    Diag d;
    d.code = FIELD_WEAK;
    d.H = H;
    return d;
}

// _measure (Euler formulation)
inline Diag measure(State& st, const Inputs& u, const Params& p) {
    Diag bad;
    if (!mag_sample(st, u, bad)) return bad;
    const V3& m = u.mag;
    if (std::fabs(u.pitch) > p.max_abs_pitch_rad) {
        Diag d;
        d.code = PITCH_BEYOND;
        d.source_available = st.source_available;
        return d;
    }
    double psi_m, H;
    magnetic_heading(m, u.roll, u.pitch, psi_m, H);
    if (H < p.min_horizontal_field_gauss) return field_weak(st, H);
    const double h = 1e-5;
    double a, b, unused;
    magnetic_heading(m, u.roll + h, u.pitch, a, unused);
    magnetic_heading(m, u.roll - h, u.pitch, b, unused);
    const double G0 = wrap_pi(a - b) / (2 * h);
    magnetic_heading(m, u.roll, u.pitch + h, a, unused);
    magnetic_heading(m, u.roll, u.pitch - h, b, unused);
    const double G1 = wrap_pi(a - b) / (2 * h);
    const double r_white = std::pow(p.mag_noise_gauss / H, 2);
    const double r_corr = std::pow(u.declination_sigma, 2) + quad2(G0, G1, u.cov_rp) + std::pow(p.mag_heading_floor_rad, 2);
    const double R = r_white + r_corr * std::max(1.0, p.mag_error_tau_s / p.mag_update_period_s);
    const double R_single = r_white + r_corr;
    const double z = wrap_2pi(psi_m + u.declination);
    if (!residual_ok(u)) { Diag d; d.code = BAD_RESIDUAL; return d; }
    const double r_uncal = uncalibrated_heading_var(m, H, u.has_residual, u.residual_sigma, p);
    if (!field_model_ok(u)) { Diag d; d.code = BAD_FIELD_MODEL; return d; }
    const double mis = u.has_field_model ? field_mismatch_var(H, levelled_down(m, u.roll, u.pitch), u.field_model) : 0.0;
    return fuse_heading(st, u, z, H, R, R_single, r_corr, r_uncal, u.has_field_model, mis, p);
}

// _predict (Euler formulation)
inline void predict(State& st, double dt, const V3& w, double phi, double th, const Mat<2, 2>& Prp, const Params& p) {
    const XH& x = st.x;
    const double sphi = std::sin(phi), cphi = std::cos(phi);
    const double cth = std::cos(th);
    const bool frozen = std::fabs(th) > p.max_abs_pitch_rad;
    const double cth_eff = std::max(std::fabs(cth), std::cos(p.max_abs_pitch_rad));
    const double wy = w[1] - x[2], wz = w[2] - x[3];
    const double psi_dot = frozen ? 0.0 : (wy * sphi + wz * cphi) / cth_eff - x[1];
    double a_v, q_v, a_b, q_b;
    gm(dt, p.vertical_rate_tau_s, p.vertical_rate_sigma_rad_s, a_v, q_v);
    gm(dt, p.gyro_bias_tau_s, p.gyro_bias_sigma_rad_s, a_b, q_b);
    PH F{};
    for (int i = 0; i < 4; ++i) F[i * NM + i] = 1.0;
    F[1] = -dt;
    F[2] = -sphi / cth_eff * dt;
    F[3] = -cphi / cth_eff * dt;
    F[1 * NM + 1] = a_v;
    F[2 * NM + 2] = a_b;
    F[3 * NM + 3] = a_b;
    const double J0 = (wy * cphi - wz * sphi) / cth_eff;
    const double J1 = (wy * sphi + wz * cphi) * std::sin(th) / (cth_eff * cth_eff);
    const double q_psi = (std::pow(p.gyro_noise_rad_s_rt_hz, 2) / (cth_eff * cth_eff)
                          + std::pow(p.heading_process_floor_rad_s_rt_hz, 2)) * dt
                         + 2.0 * p.attitude_error_tau_s * quad2(J0, J1, Prp) * dt;
    PH P = fpft(F, st.P, 4);
    P[0] += q_psi;
    P[1 * NM + 1] += q_v;
    P[2 * NM + 2] += q_b;
    P[3 * NM + 3] += q_b;
    const XH xn{wrap_2pi(x[0] + psi_dot * dt), x[1] * a_v, x[2], x[3], 0.0};
    st.x = xn;
    st.P = P;
}

// polar_heading_step, Euler formulation (q_P_from_body not given)
inline Diag euler_step(State& held, const Inputs& u, const Params& p) {
    Diag d;
    if (!(finite3(u.gyro) && std::isfinite(u.time_s) && std::isfinite(u.roll) && std::isfinite(u.pitch))) {
        d.code = NON_FINITE_INPUT;
        d.source_available = held.source_available;
        return d;
    }
    State st = held;
    if (st.has_time) {
        const double dt = u.time_s - st.time_s;
        if (dt <= 0.0) {
            d.code = TIME_NOT_INCREASING;
            d.dt_s = dt;
            return d;
        }
        if (dt <= p.max_dt_s && st.initialised)
            predict(st, dt, u.gyro, u.roll, u.pitch, u.cov_rp, p);
        else if (st.initialised)
            unseen(st, dt, p);
    }
    st.has_time = true;
    st.time_s = u.time_s;
    if (!u.has_mag || (st.has_last_mag && u.time_s - st.last_mag_time_s + 1e-9 < p.mag_update_period_s)) {
        d.source_available = st.source_available;
        held = st;
        return d;
    }
    d = measure(st, u, p);
    if (d.code != BAD_DECLINATION && d.code != BAD_RESIDUAL && d.code != BAD_FIELD_MODEL) held = st;
    return d;
}

// --- platform formulation -------------------------------------------------------------------------

// _own_attitude
inline Q4 own_attitude(const Q4& q_prev, const V3& angle_body, const Q4& q_P) {
    const Q4 q_pred = quat_normalize(quat_mul(q_prev, quat_from_rotvec(angle_body)));
    const M3 Cp = dcm_from_quat(q_pred), Ca = dcm_from_quat(q_P);
    const V3 g_pred{Cp[6], Cp[7], Cp[8]};
    const V3 g_att{Ca[6], Ca[7], Ca[8]};
    const V3 axis = cross3(g_att, g_pred);
    const double s = norm3(axis), c = dot3(g_att, g_pred);
    if (s < 1e-12) return c > 0.0 ? q_pred : q_P;
    const double ang = std::atan2(s, c);
    const V3 rv{axis[0] / s * ang, axis[1] / s * ang, axis[2] / s * ang};
    return quat_normalize(quat_mul(q_pred, quat_from_rotvec(rv)));
}

// _to_platform
inline void to_platform(State& st, const Q4& q, const Params& p) {
    XH x{};
    PH P = prior_P(0.0, p, 5);
    if (st.initialised) {
        x[0] = wrap_2pi(st.x[0] - yaw_of(q));
        x[1] = st.x[1];
        for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 2; ++j) P[i * NM + j] = st.P[i * NM + j];
    }
    st.platform = true;
    st.n = 5;
    st.x = x;
    st.P = P;
}

// _predict_platform
inline void predict_platform(State& st, double dt, const Params& p) {
    const M3 C_PB = dcm_from_quat(st.q_P_from_body);
    const XH x = st.x;
    double a_v, q_v, a_b, q_b;
    gm(dt, p.vertical_rate_tau_s, p.vertical_rate_sigma_rad_s, a_v, q_v);
    gm(dt, p.gyro_bias_tau_s, p.gyro_bias_sigma_rad_s, a_b, q_b);
    PH F{};
    F[0] = 1.0;
    F[1 * NM + 1] = a_v;
    for (int i = 2; i < 5; ++i) F[i * NM + i] = a_b;
    F[1] = -dt;
    for (int j = 0; j < 3; ++j) F[2 + j] = -C_PB[6 + j] * dt;
    PH P = fpft(F, st.P, 5);
    P[0] += (std::pow(p.gyro_noise_rad_s_rt_hz, 2) + std::pow(p.heading_process_floor_rad_s_rt_hz, 2)) * dt;
    P[1 * NM + 1] += q_v;
    for (int i = 2; i < 5; ++i) P[i * NM + i] += q_b;
    XH xn = x;
    xn[0] = wrap_2pi(x[0] - x[1] * dt);
    xn[1] = x[1] * a_v;
    for (int i = 2; i < 5; ++i) xn[i] = x[i] * a_b;
    st.x = xn;
    st.P = P;
}

// _measure_platform
inline Diag measure_platform(State& st, const Inputs& u, const Q4& q, const Params& p) {
    Diag bad;
    if (!mag_sample(st, u, bad)) return bad;
    const V3& m = u.mag;
    const M3 C_PB = dcm_from_quat(q);
    M3 C_lev;
    Mat<2, 2> P_tilt;
    if (u.level_with_roll_pitch) {
        if (!(std::isfinite(u.roll) && std::isfinite(u.pitch))) {
            Diag d;
            d.code = NON_FINITE_INPUT;
            d.source_available = st.source_available;
            return d;
        }
        C_lev = dcm_from_euler(u.roll, u.pitch, euler_from_dcm(C_PB)[2]);
        P_tilt = u.cov_rp;
    } else {
        C_lev = C_PB;
        const M3 Pe = u.has_cov_att ? u.cov_att : M3{};
        const M3 A = mm<3, 3, 3>(mm<3, 3, 3>(C_PB, Pe), tr<3, 3>(C_PB));
        P_tilt = {A[0], A[1], A[3], A[4]};
    }
    const V3 mp = mv<3, 3>(C_lev, m);
    const double H = std::hypot(mp[0], mp[1]);
    if (H < p.min_horizontal_field_gauss) return field_weak(st, H);
    const double k = -mp[2] / (H * H);
    const double G0 = k * mp[0], G1 = k * mp[1];
    const double r_white = std::pow(p.mag_noise_gauss / H, 2);
    const double r_nav = std::pow(u.declination_sigma, 2);
    const double r_body = quad2(G0, G1, P_tilt) + std::pow(p.mag_heading_floor_rad, 2);
    const double r_corr = r_nav + r_body;
    const V3 wr{u.gyro[0] - st.x[2], u.gyro[1] - st.x[3], u.gyro[2] - st.x[4]};
    const double rate = norm3(wr);
    double tau_body = p.mag_error_tau_s;
    if (p.mag_error_turn_rad > 0.0 && rate * tau_body > p.mag_error_turn_rad) tau_body = p.mag_error_turn_rad / rate;
    const double R = (r_white + r_nav * std::max(1.0, p.mag_error_tau_s / p.mag_update_period_s)
                      + r_body * std::max(1.0, tau_body / p.mag_update_period_s));
    const double R_single = r_white + r_corr;
    const double z = wrap_2pi(-std::atan2(mp[1], mp[0]) + u.declination);
    if (!residual_ok(u)) { Diag d; d.code = BAD_RESIDUAL; return d; }
    const double r_uncal = uncalibrated_heading_var(m, H, u.has_residual, u.residual_sigma, p);
    if (!field_model_ok(u)) { Diag d; d.code = BAD_FIELD_MODEL; return d; }
    const double mis = u.has_field_model ? field_mismatch_var(H, mp[2], u.field_model) : 0.0;
    return fuse_heading(st, u, z, H, R, R_single, r_corr, r_uncal, u.has_field_model, mis, p);
}

// _platform_step (q_P finite with a norm > 0: the binding hands anything else to the reference)
inline Diag platform_step(State& held, const Inputs& u, const Params& p) {
    Diag d;
    if (!(std::isfinite(u.q_P[0]) && std::isfinite(u.q_P[1]) && std::isfinite(u.q_P[2]) && std::isfinite(u.q_P[3]) &&
          std::isfinite(u.time_s) && finite3(u.gyro))) {
        d.code = NON_FINITE_INPUT;
        d.source_available = held.source_available;
        return d;
    }
    const double nq = std::sqrt(dot4(u.q_P));
    const Q4 q_P{u.q_P[0] / nq, u.q_P[1] / nq, u.q_P[2] / nq, u.q_P[3] / nq};
    State st = held;
    if (!st.platform) to_platform(st, q_P, p);
    Q4 q = q_P;
    if (st.has_time) {
        const double dt = u.time_s - st.time_s;
        if (dt <= 0.0) {
            d.code = TIME_NOT_INCREASING;
            d.dt_s = dt;
            held = st;
            return d;
        }
        if (dt <= p.max_dt_s && st.has_q) {
            const V3 ang{(u.gyro[0] - st.x[2]) * dt, (u.gyro[1] - st.x[3]) * dt, (u.gyro[2] - st.x[4]) * dt};
            q = own_attitude(st.q_P_from_body, ang, q_P);
            if (st.initialised) predict_platform(st, dt, p);
        } else if (st.initialised) {
            unseen(st, dt, p);
        }
    }
    st.has_time = true;
    st.time_s = u.time_s;
    st.has_q = true;
    st.q_P_from_body = q;
    if (!u.has_mag || (st.has_last_mag && u.time_s - st.last_mag_time_s + 1e-9 < p.mag_update_period_s)) {
        d.source_available = st.source_available;
        held = st;
        return d;
    }
    if (st.has_rejected_since && st.has_last_mag && u.time_s - st.last_mag_time_s > WITHHELD_AFTER_S)
        st.has_rejected_since = false;  // the magnetometer was withheld meanwhile: its rejections start over
    d = measure_platform(st, u, q, p);
    if (d.code != BAD_DECLINATION && d.code != BAD_RESIDUAL && d.code != BAD_FIELD_MODEL) held = st;
    return d;
}

// polar_heading_step
inline Diag step(State& held, const Inputs& u, const Params& p) {
    return u.has_q ? platform_step(held, u, p) : euler_step(held, u, p);
}

}  // namespace polar_heading
}  // namespace azimuthd
