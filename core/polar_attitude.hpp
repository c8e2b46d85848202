// Method C's attitude filter (the polar-capable roll/pitch filter): the compiled twin of
// estimators/polar_attitude.py, which stays the reference and holds the derivation (25 error states
// x = [eps(3), db_g(3), da_v(3), dw_ie_P(3), dw_eP_P(3), db_a(3), dg(1), ds_g(3), dr_g(3)], the nominal
// mechanisation per sample, the specific-force update every update_period_s with its gate, re-entry
// test, covariance matching, platform-yaw cap and re-levelling at rest; holes bridged, gaps unseen).
// Every scalar expression is the reference's, in its order. The 25 x 25 products skip the entries
// that are zero by construction (F is the identity but for the attitude rows, the Gauss-Markov
// diagonal and the bias rows' bias-rate column; H has 10 non-zero columns; the Joseph form is written (I - K H) P (I - K H)^T as
// P - K (H P), then minus (.. H^T) K^T): the same sums without their exact zeros. numpy's BLAS sums
// and fuses in its own order, so the two agree to rounding: tests/test_core_polar_attitude.py asserts
// 1e-9 relative (covariances against sqrt(P_ii P_jj)).
#pragma once

#include <cmath>

#include "ahrs_math.hpp"

namespace azimuthd {
namespace polar {

constexpr int NS = 25;   // error states
constexpr int NX = 22;   // x_hat: every state but the attitude error
using PMat = Mat<NS, NS>;
using XVec = std::array<double, NX>;

// estimators.polar_attitude.PolarAttitudeParams (the fields the filter reads)
struct Params {
    double update_period_s, init_period_s, gyro_noise_rad_s_rt_hz, gyro_bias_init_sigma_rad_s,
        gyro_bias_sigma_rad_s, gyro_bias_tau_s, gyro_bias_rate_sigma_rad_s2, gyro_bias_rate_tau_s, takeoff_bias_step_sigma_rad_s,
        accel_noise_m_s2, accel_meas_floor_m_s2, vehicle_accel_sigma_m_s2,
        vehicle_accel_tau_s, manoeuvre_speed_m_s, earth_rate_sigma_rad_s, earth_rate_tau_s,
        transport_rate_sigma_rad_s, transport_rate_tau_s, accel_bias_sigma_m_s2, accel_bias_tau_s, gyro_scale_sigma,
        gyro_scale_tau_s, gravity_variation_sigma_m_s2, gravity_variation_tau_s, gravity_m_s2, init_tilt_sigma_rad,
        init_yaw_sigma_rad, max_platform_yaw_sigma_rad, gate_chi2, reentry_settle_chi2;
    long reentry_max_wait_updates;
    double reentry_match_gain, max_dt_s, unseen_rate_sigma_rad_s, relevel_rest_s, relevel_max_rate_rad_s;
    bool relevel_allowed;
    double relevel_norm_tol_m_s2, sample_span_max_s, gap_rate_walk_rad_s2_rt_hz, unseen_max_sigma_rad;
};

// estimators.polar_attitude.PolarAttitudeState (has_*: the reference's Optional fields)
struct State {
    bool initialised = false;
    bool has_time = false;
    double time_s = 0.0;
    Q4 q_P_from_body{1.0, 0.0, 0.0, 0.0};
    XVec x_hat{};
    PMat P{};
    bool has_gyro_prev = false;
    V3 gyro_prev_rad_s{};
    long acc_n = 0;
    double acc_dt_s = 0.0;
    V3 acc_f_sum_m_s2{};
    V3 acc_f_sq_sum_m2_s4{};
    V3 acc_down_sum{};
    Q4 acc_q_b0_from_b{1.0, 0.0, 0.0, 0.0};
    M3 acc_C_BP_start{1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0};
    long n_updates = 0, n_rejected = 0;
    bool has_bias_prior_sigma = false;
    double bias_prior_sigma_rad_s = 0.0;
    long gated_run = 0, reentry_wait = 0;
    bool has_z_prev = false;
    V3 z_prev_m_s2{};
    long rest_gated_run = 0;
    V3 rest_f_sum_m_s2{};
    double rest_s = 0.0;
    long n_relevels = 0;
    bool has_sample_dt = false;
    double sample_dt_s = 0.0;
    bool bias_rate_opened = false;
};

// what a step did: the reference's PolarAttitudeDiag.reason, as a code (the Python face words it)
enum Code : int {
    SAMPLE = 0,               // integrated, no update due (PolarAttitudeDiag())
    LEVELLING = 1,            // "levelling"
    LEVELLED = 2,             // "levelled"
    NON_FINITE = 3,           // "non-finite sample"
    RESTARTED = 4,            // "increments restarted"
    TIME_NOT_INCREASING = 5,  // "time not increasing (dt=%.6f s)"
    GAP = 6,                  // "gap of %.3f s not integrated; attitude sigma widened"
    UPDATE = 7,               // a specific-force update was attempted (the fields below)
};
enum Why : int { FUSED = 0, GATED_OUT = 1, NOT_SETTLED = 2, RELEVELLED = 3 };

struct Diag {
    int code = SAMPLE;
    double dt_s = 0.0;
    bool fused = false;
    V3 innovation_m_s2{};
    double test_ratio = NAN, settle_ratio = NAN, accel_var_raised_m2_s4 = 0.0;
    int why = FUSED;
    double relevel_rad = 0.0;
};

// --- small pieces ---------------------------------------------------------------------------------

inline V3 add3(const V3& a, const V3& b) { return {a[0] + b[0], a[1] + b[1], a[2] + b[2]}; }
inline V3 sub3(const V3& a, const V3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
inline V3 scale3(const V3& a, double s) { return {a[0] * s, a[1] * s, a[2] * s}; }
inline V3 div3(const V3& a, double s) { return {a[0] / s, a[1] / s, a[2] / s}; }
inline double dot3(const V3& a, const V3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
inline V3 cross3(const V3& a, const V3& b) {  // np.cross
    return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
// x^T A x for a 3x3 A: (x @ A) @ x
inline double quad3(const V3& x, const M3& A) {
    V3 xa{};
    for (int j = 0; j < 3; ++j) xa[j] = x[0] * A[j] + x[1] * A[3 + j] + x[2] * A[6 + j];
    return dot3(xa, x);
}
inline M3 att_block(const PMat& P) {
    M3 B{};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) B[i * 3 + j] = P[i * NS + j];
    return B;
}
inline V3 col2(const M3& C) { return {C[2], C[5], C[8]}; }

// rotations.rotvec_from_quat: the shortest rotation of a (normalised, w >= 0) quaternion
inline V3 rotvec_from_quat(const Q4& q_in) {
    const Q4 q = quat_normalize(q_in);
    const V3 v{q[1], q[2], q[3]};
    const double s = std::sqrt(dot3(v, v));
    if (s < 1e-12) return {2.0 * v[0], 2.0 * v[1], 2.0 * v[2]};
    const double angle = 2.0 * std::atan2(s, q[0]);
    return scale3(v, angle / s);
}

// C_BP[:, 2] = third row of C_PB for q = q_P_from_body
inline V3 down_in_body(const Q4& q) {
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    return {2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)};
}

inline M3 dcm_T(const Q4& q) { return tr<3, 3>(dcm_from_quat(q)); }

inline void symmetrise_p(PMat& P) { symmetrise<NS>(P); }

// _gm_diagonals: transition and process-noise diagonals of the Gauss-Markov states over dt
inline void gm_diagonals(double dt, const Params& p, double F[NS], double Q[NS]) {
    for (int i = 0; i < NS; ++i) { F[i] = 1.0; Q[i] = 0.0; }
    const struct { int a, b; double tau, sig; } blocks[] = {
        {3, 6, p.gyro_bias_tau_s, p.gyro_bias_sigma_rad_s},
        {6, 9, p.vehicle_accel_tau_s, p.vehicle_accel_sigma_m_s2},
        {9, 12, p.earth_rate_tau_s, p.earth_rate_sigma_rad_s},
        {12, 15, p.transport_rate_tau_s, p.transport_rate_sigma_rad_s},
        {15, 18, p.accel_bias_tau_s, p.accel_bias_sigma_m_s2},
        {18, 19, p.gravity_variation_tau_s, p.gravity_variation_sigma_m_s2},
        {19, 22, p.gyro_scale_tau_s, p.gyro_scale_sigma},
        {22, 25, p.gyro_bias_rate_tau_s, p.gyro_bias_rate_sigma_rad_s2}};
    for (const auto& b : blocks) {
        const double phi = std::exp(-dt / b.tau);
        const double q = b.sig * b.sig * (1.0 - phi * phi);
        for (int i = b.a; i < b.b; ++i) { F[i] = phi; Q[i] = q; }
    }
}

// _initial_covariance
inline PMat initial_covariance(const M3& C_BP, const Params& p, double tilt_sigma, bool has_bias_sigma,
                               double bias_sigma) {
    PMat P{};
    const M3 Pp{std::pow(tilt_sigma, 2), 0.0, 0.0, 0.0, std::pow(tilt_sigma, 2), 0.0, 0.0, 0.0,
                std::pow(p.init_yaw_sigma_rad, 2)};
    const M3 A = mm<3, 3, 3>(mm<3, 3, 3>(C_BP, Pp), tr<3, 3>(C_BP));
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) P[i * NS + j] = A[i * 3 + j];
    const double sb = has_bias_sigma ? bias_sigma : p.gyro_bias_init_sigma_rad_s;
    const double d[NS] = {0, 0, 0,
                          std::pow(sb, 2), std::pow(sb, 2), std::pow(sb, 2),
                          std::pow(p.vehicle_accel_sigma_m_s2, 2), std::pow(p.vehicle_accel_sigma_m_s2, 2),
                          std::pow(p.vehicle_accel_sigma_m_s2, 2),
                          std::pow(p.earth_rate_sigma_rad_s, 2), std::pow(p.earth_rate_sigma_rad_s, 2),
                          std::pow(p.earth_rate_sigma_rad_s, 2),
                          std::pow(p.transport_rate_sigma_rad_s, 2), std::pow(p.transport_rate_sigma_rad_s, 2),
                          std::pow(p.transport_rate_sigma_rad_s, 2),
                          std::pow(p.accel_bias_sigma_m_s2, 2), std::pow(p.accel_bias_sigma_m_s2, 2),
                          std::pow(p.accel_bias_sigma_m_s2, 2),
                          std::pow(p.gravity_variation_sigma_m_s2, 2),
                          std::pow(p.gyro_scale_sigma, 2), std::pow(p.gyro_scale_sigma, 2),
                          std::pow(p.gyro_scale_sigma, 2),
                          std::pow(p.gyro_bias_rate_sigma_rad_s2, 2), std::pow(p.gyro_bias_rate_sigma_rad_s2, 2),
                          std::pow(p.gyro_bias_rate_sigma_rad_s2, 2)};
    for (int i = 3; i < NS; ++i) P[i * NS + i] = d[i];
    return P;
}

// _ramp_bias: the nominal gyro bias and its rate over dt (b' = r, r' = -r / tau_r)
inline void ramp_bias(XVec& x, double dt, const Params& p) {
    const double phi = std::exp(-dt / p.gyro_bias_rate_tau_s);
    const double c = p.gyro_bias_rate_tau_s * (1.0 - phi);
    for (int i = 0; i < 3; ++i) x[i] += x[19 + i] * c;
    for (int i = 19; i < 22; ++i) x[i] *= phi;
}

// --- init, init_at, unseen --------------------------------------------------------------------------

// polar_attitude_init (arguments checked by the caller, as the reference checks them)
inline State init(bool has_bias, const V3& bias, bool has_bias_sigma, double bias_sigma) {
    State s;
    if (has_bias)
        for (int i = 0; i < 3; ++i) s.x_hat[i] = bias[i];
    s.has_bias_prior_sigma = has_bias_sigma;
    s.bias_prior_sigma_rad_s = has_bias_sigma ? bias_sigma : 0.0;
    return s;
}

// polar_attitude_init_at
inline State init_at(double time_s, double roll, double pitch, double tilt_sigma, const Params& p, bool has_bias,
                     const V3& bias, bool has_bias_sigma, double bias_sigma) {
    State s = init(has_bias, bias, has_bias_sigma, bias_sigma);
    const Q4 q = quat_from_euler(roll, pitch, 0.0);
    const M3 C_BP = dcm_T(q);
    s.P = initial_covariance(C_BP, p, tilt_sigma, has_bias_sigma, bias_sigma);
    s.initialised = true;
    s.has_time = true;
    s.time_s = time_s;
    s.q_P_from_body = q;
    s.has_gyro_prev = false;
    s.acc_C_BP_start = C_BP;
    return s;
}

inline void reset_interval(State& s, const M3& C_BP) {
    s.acc_n = 0;
    s.acc_dt_s = 0.0;
    s.acc_f_sum_m_s2 = {0.0, 0.0, 0.0};
    s.acc_down_sum = {0.0, 0.0, 0.0};
    s.acc_q_b0_from_b = {1.0, 0.0, 0.0, 0.0};
    s.acc_C_BP_start = C_BP;
}

// polar_attitude_unseen (unseen_s checked finite and >= 0 by the caller)
inline void unseen(State& s, double unseen_s, const Params& p) {
    if (!s.initialised) return;
    double F[NS], Q[NS];
    gm_diagonals(unseen_s, p, F, Q);
    PMat P;
    for (int i = 0; i < NS; ++i)
        for (int j = 0; j < NS; ++j) P[i * NS + j] = F[i] * s.P[i * NS + j] * F[j];
    for (int i = 0; i < NS; ++i) P[i * NS + i] += Q[i];
    const double sg = std::min(p.unseen_rate_sigma_rad_s * unseen_s, p.unseen_max_sigma_rad);
    for (int i = 0; i < 3; ++i) P[i * NS + i] += sg * sg;
    const double decay = std::exp(-unseen_s / p.vehicle_accel_tau_s);
    for (int i = 3; i < 6; ++i) s.x_hat[i] *= decay;
    ramp_bias(s.x_hat, unseen_s, p);
    symmetrise_p(P);
    s.P = P;
    s.has_time = false;
    s.has_gyro_prev = false;
    s.has_sample_dt = false;
    reset_interval(s, dcm_T(s.q_P_from_body));
}

// --- the update -----------------------------------------------------------------------------------

// _down_mean_over_sample (Simpson's rule on start, middle and end attitude)
inline V3 down_mean_over_sample(const Q4& q0, const Q4& q1, const V3& W_hat, double dt, const V3& dtheta) {
    const Q4 qm = quat_mul(quat_from_rotvec(scale3(scale3(W_hat, -0.5), dt)),
                           quat_mul(q0, quat_from_rotvec(scale3(dtheta, 0.5))));
    const V3 d0 = down_in_body(q0), dm = down_in_body(qm), d1 = down_in_body(q1);
    return {(d0[0] + 4.0 * dm[0] + d1[0]) / 6.0, (d0[1] + 4.0 * dm[1] + d1[1]) / 6.0,
            (d0[2] + 4.0 * dm[2] + d1[2]) / 6.0};
}

// _bridge_variance_rad2
inline double bridge_variance(const V3& w_prev, const V3& w, double dt, const Params& p) {
    double m = std::fabs(w[0] - w_prev[0]);
    for (int i = 1; i < 3; ++i) m = std::max(m, std::fabs(w[i] - w_prev[i]));
    const double step = m * dt;
    return std::pow(p.gap_rate_walk_rad_s2_rt_hz, 2) * std::pow(dt, 3) / 12.0 + step * step / 12.0;
}

// _cap_platform_yaw: D P D^T, D = I + (s - 1) d d^T on the attitude block
inline void cap_platform_yaw(PMat& P, const V3& d, double cap) {
    const double var = quad3(d, att_block(P));
    if (var <= cap * cap) return;
    const double s = cap / std::sqrt(var);
    M3 D{};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) D[i * 3 + j] = (i == j ? 1.0 : 0.0) + (s - 1.0) * (d[i] * d[j]);
    PMat A = P;  // D P: rows 0:3
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < NS; ++j)
            A[i * NS + j] = D[i * 3] * P[j] + D[i * 3 + 1] * P[NS + j] + D[i * 3 + 2] * P[2 * NS + j];
    for (int i = 0; i < NS; ++i) {  // (D P) D^T: columns 0:3
        const double a0 = A[i * NS], a1 = A[i * NS + 1], a2 = A[i * NS + 2];
        for (int j = 0; j < 3; ++j) A[i * NS + j] = a0 * D[j * 3] + a1 * D[j * 3 + 1] + a2 * D[j * 3 + 2];
    }
    P = A;
}

// the non-zero columns of H (attitude 0:3, a_v 6:9, b_a 15:18, dg 18)
constexpr int HC[10] = {0, 1, 2, 6, 7, 8, 15, 16, 17, 18};
using HMat = std::array<double, 3 * 10>;   // H[:, HC]

// H @ P @ H^T + r I  ((H P) H^T, H given on its non-zero columns)
inline M3 innovation_cov(const HMat& H, const PMat& P, double r) {
    Mat<3, NS> HP{};
    for (int m = 0; m < 3; ++m)
        for (int j = 0; j < NS; ++j) {
            double a = H[m * 10] * P[HC[0] * NS + j];
            for (int k = 1; k < 10; ++k) a = a + H[m * 10 + k] * P[HC[k] * NS + j];
            HP[m * NS + j] = a;
        }
    M3 S{};
    for (int m = 0; m < 3; ++m)
        for (int n = 0; n < 3; ++n) {
            double a = HP[m * NS + HC[0]] * H[n * 10];
            for (int k = 1; k < 10; ++k) a = a + HP[m * NS + HC[k]] * H[n * 10 + k];
            S[m * 3 + n] = a + (m == n ? r : 0.0);
        }
    return S;
}

// _reentry: (fuse allowed, settle ratio)
inline bool reentry(const State& st, const V3& z, double r, double q_av, const Params& p, double& ratio) {
    ratio = NAN;
    if (st.gated_run == 0 || !st.has_z_prev || p.reentry_max_wait_updates == 0) return true;
    const V3 d = sub3(z, st.z_prev_m_s2);
    ratio = dot3(d, d) / (2.0 * r + q_av) / p.reentry_settle_chi2;
    if (st.reentry_wait >= p.reentry_max_wait_updates) return true;
    return ratio <= 1.0;
}

// _match_gated_accel: raise a_v's variance along z; returns the variance added
inline double match_gated_accel(PMat& P, const V3& z, const M3& S, double gain) {
    if (gain == 0.0) return 0.0;
    const double zz = dot3(z, z);
    if (!(zz > 0.0)) return 0.0;
    const V3 u = div3(z, std::sqrt(zz));
    const double e = gain * (zz - quad3(u, S));
    if (e <= 0.0) return 0.0;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) P[(6 + i) * NS + 6 + j] += e * (u[i] * u[j]);
    return e;
}

// _at_rest
inline bool at_rest(const State& st, const V3& f_c, double g, const V3& w_mean, const V3& z, double r, double q_av,
                    const Params& p) {
    if (std::fabs(norm3(f_c) - g) > p.relevel_norm_tol_m_s2) return false;
    if (norm3(w_mean) > p.relevel_max_rate_rad_s) return false;
    if (!st.has_z_prev) return true;
    const V3 d = sub3(z, st.z_prev_m_s2);
    return dot3(d, d) / (2.0 * r + q_av) <= p.reentry_settle_chi2;
}

// _relevel: roll/pitch from the accelerometer after a sustained gated-out rest; returns the angle
inline double relevel(State& st, const Params& p) {
    const V3 f = div3(st.rest_f_sum_m_s2, static_cast<double>(st.rest_gated_run));
    const M3 C_BP = dcm_T(st.q_P_from_body);
    const V3 d_hat = col2(C_BP);
    const double nf = norm3(f);
    const V3 d_m{-f[0] / nf, -f[1] / nf, -f[2] / nf};
    V3 axis = cross3(d_m, d_hat);
    double s_ang = norm3(axis);
    const double c_ang = dot3(d_m, d_hat);
    const double angle = std::atan2(s_ang, c_ang);
    if (s_ang < 1e-9) {
        axis = cross3(d_m, std::fabs(d_m[0]) < 0.9 ? V3{1.0, 0.0, 0.0} : V3{0.0, 1.0, 0.0});
        s_ang = norm3(axis);
    }
    const V3 eps = scale3(div3(axis, s_ang), angle);
    const Q4 q = quat_unit(quat_mul(st.q_P_from_body, quat_from_rotvec(eps)));
    const double a_max = std::sqrt(2.0 * p.gravity_m_s2 * p.relevel_norm_tol_m_s2);
    const double sig_t = std::hypot(a_max / 3.0, p.accel_bias_sigma_m_s2) / p.gravity_m_s2;
    const double v_vert = quad3(d_hat, att_block(st.P));
    PMat& P = st.P;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < NS; ++j) { P[i * NS + j] = 0.0; P[j * NS + i] = 0.0; }
    const double st2 = std::pow(sig_t, 2);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            const double o = d_m[i] * d_m[j];
            P[i * NS + j] = st2 * ((i == j ? 1.0 : 0.0) - o) + v_vert * o;
        }
    for (int i = 6; i < 9; ++i)
        for (int j = 0; j < NS; ++j) { P[i * NS + j] = 0.0; P[j * NS + i] = 0.0; }
    for (int i = 6; i < 9; ++i) P[i * NS + i] = 1.0 * std::pow(p.vehicle_accel_sigma_m_s2, 2);
    for (int i = 3; i < 6; ++i) st.x_hat[i] = 0.0;
    st.q_P_from_body = q;
    st.acc_C_BP_start = dcm_T(q);
    st.gated_run = 0;
    st.reentry_wait = 0;
    st.has_z_prev = false;
    st.rest_gated_run = 0;
    st.rest_f_sum_m_s2 = {0.0, 0.0, 0.0};
    st.rest_s = 0.0;
    st.n_relevels += 1;
    return angle;
}

// _open_bias_rate: the bias rate's and the bias's priors for flight, once per take-off (relevel_allowed
// going False)
inline void open_bias_rate(State& st, const Params& p) {
    if (p.relevel_allowed) {
        st.bias_rate_opened = false;
        return;
    }
    if (st.bias_rate_opened) return;
    for (int i = 22; i < 25; ++i)
        for (int j = 0; j < NS; ++j) { st.P[i * NS + j] = 0.0; st.P[j * NS + i] = 0.0; }
    for (int i = 22; i < 25; ++i) st.P[i * NS + i] = 1.0 * std::pow(p.gyro_bias_rate_sigma_rad_s2, 2);
    for (int i = 3; i < 6; ++i) st.P[i * NS + i] += 1.0 * std::pow(p.takeoff_bias_step_sigma_rad_s, 2);
    st.bias_rate_opened = true;
}

// _update: covariance over the interval, then the specific-force update
inline Diag update(State& st, const Params& p) {
    open_bias_rate(st, p);
    Diag dg;
    dg.code = UPDATE;
    const double T = st.acc_dt_s;
    const M3 R_b0_b = dcm_from_quat(st.acc_q_b0_from_b);
    const M3 C_BP_end = dcm_T(st.q_P_from_body);
    const M3& C_BP_0 = st.acc_C_BP_start;

    // --- covariance propagation over T ---------------------------------------------------------
    const M3 Rt = tr<3, 3>(R_b0_b);
    const V3 theta = rotvec_from_quat(st.acc_q_b0_from_b);
    const M3 RtC0 = mm<3, 3, 3>(Rt, C_BP_0);
    // F's attitude rows on their non-zero columns: att 0:3, bg 3:6, wie 9:12, wep 12:15, sg 19:22, br 22:25
    constexpr int FC[18] = {0, 1, 2, 3, 4, 5, 9, 10, 11, 12, 13, 14, 19, 20, 21, 22, 23, 24};
    double Fa[3][18];
    const double hT = -0.5 * T;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            const double I_Rt = (i == j ? 1.0 : 0.0) + Rt[i * 3 + j];
            const double coupling = hT * (C_BP_end[i * 3 + j] + RtC0[i * 3 + j]);
            Fa[i][j] = Rt[i * 3 + j];
            Fa[i][3 + j] = hT * I_Rt;
            Fa[i][6 + j] = coupling;
            Fa[i][9 + j] = coupling;
            Fa[i][12 + j] = -0.5 * I_Rt * theta[j];
            Fa[i][15 + j] = (i == j ? -0.5 * T * T : 0.0);
        }
    // the bias rows: phi_bg on the diagonal and tau_r (1 - phi_r) on the bias rate (F[I_BG, I_BR])
    const double c_br = p.gyro_bias_rate_tau_s * (1.0 - std::exp(-T / p.gyro_bias_rate_tau_s));
    double phi[NS], Q[NS];
    gm_diagonals(T, p, phi, Q);
    Q[0] = Q[1] = Q[2] = std::pow(p.gyro_noise_rad_s_rt_hz, 2) * T;
    const PMat& P0 = st.P;
    PMat A;  // F P
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < NS; ++j) {
            double a = Fa[i][0] * P0[FC[0] * NS + j];
            for (int k = 1; k < 18; ++k) a = a + Fa[i][k] * P0[FC[k] * NS + j];
            A[i * NS + j] = a;
        }
    for (int i = 3; i < NS; ++i)
        for (int j = 0; j < NS; ++j) A[i * NS + j] = phi[i] * P0[i * NS + j];
    for (int i = 3; i < 6; ++i)
        for (int j = 0; j < NS; ++j) A[i * NS + j] = A[i * NS + j] + c_br * P0[(i + 19) * NS + j];
    PMat P;  // (F P) F^T
    for (int i = 0; i < NS; ++i) {
        for (int j = 0; j < 3; ++j) {
            double a = A[i * NS + FC[0]] * Fa[j][0];
            for (int k = 1; k < 18; ++k) a = a + A[i * NS + FC[k]] * Fa[j][k];
            P[i * NS + j] = a;
        }
        for (int j = 3; j < NS; ++j) P[i * NS + j] = A[i * NS + j] * phi[j];
        for (int j = 3; j < 6; ++j) P[i * NS + j] = P[i * NS + j] + A[i * NS + j + 19] * c_br;
    }
    for (int i = 0; i < NS; ++i) P[i * NS + i] += Q[i];
    // manoeuvre-adaptive vehicle acceleration
    const V3 w_mean = div3(theta, T);
    const double s0 = std::pow(p.vehicle_accel_sigma_m_s2, 2);
    const double V = p.manoeuvre_speed_m_s;
    const double var_man[3] = {s0, s0 + std::pow(w_mean[2] * V, 2), s0 + std::pow(w_mean[1] * V, 2)};
    for (int i = 0; i < 3; ++i)
        if (P[(6 + i) * NS + 6 + i] < var_man[i]) P[(6 + i) * NS + 6 + i] = var_man[i];

    // --- specific-force measurement ------------------------------------------------------------
    const XVec xh = st.x_hat;
    const double g = p.gravity_m_s2 + xh[15];
    const double n = static_cast<double>(st.acc_n);
    const V3 down_mean = div3(st.acc_down_sum, n);
    const V3 f_mean = div3(st.acc_f_sum_m_s2, n);
    V3 z;
    for (int i = 0; i < 3; ++i) z[i] = f_mean[i] - ((xh[12 + i] + xh[3 + i]) - g * down_mean[i]);
    const V3 d_end = col2(C_BP_end);
    const V3 gB = scale3(d_end, g);
    HMat H{};
    const M3 sk = skew(gB);
    for (int m = 0; m < 3; ++m) {
        for (int j = 0; j < 3; ++j) H[m * 10 + j] = -sk[m * 3 + j];
        H[m * 10 + 3 + m] = 1.0;
        H[m * 10 + 6 + m] = 1.0;
        H[m * 10 + 9] = -d_end[m];
    }
    const double r = std::max(std::pow(p.accel_noise_m_s2, 2) / n, std::pow(p.accel_meas_floor_m_s2, 2));
    M3 S = innovation_cov(H, P, r);
    M3 S_inv = inv<3>(S);
    const double nis = quad3(z, S_inv);
    const double ratio = nis / p.gate_chi2;
    const bool gate_ok = ratio <= 1.0;
    const double q_av = s0 * (1.0 - std::pow(phi[6], 2));
    double settle_ratio;
    const bool reentry_ok = reentry(st, z, r, q_av, p, settle_ratio);
    const bool fused = gate_ok && reentry_ok;
    Q4 q_new = st.q_P_from_body;
    XVec x_new = xh;
    double raised = 0.0;
    if (fused && st.gated_run > 0 && p.reentry_match_gain > 0.0) {
        raised = match_gated_accel(P, z, S, p.reentry_match_gain);
        S = innovation_cov(H, P, r);
        S_inv = inv<3>(S);
    }
    if (fused) {
        // K = (P H^T) S^-1
        Mat<NS, 3> PHt{};
        for (int i = 0; i < NS; ++i)
            for (int m = 0; m < 3; ++m) {
                double a = P[i * NS + HC[0]] * H[m * 10];
                for (int k = 1; k < 10; ++k) a = a + P[i * NS + HC[k]] * H[m * 10 + k];
                PHt[i * 3 + m] = a;
            }
        const Mat<NS, 3> K = mm<NS, 3, 3>(PHt, S_inv);
        const std::array<double, NS> dx = mv<NS, 3>(K, z);
        // Joseph form: M = (I - K H) P = P - K (H P); P' = M (I - K H)^T + K (r I) K^T
        Mat<3, NS> HP{};
        for (int m = 0; m < 3; ++m)
            for (int j = 0; j < NS; ++j) {
                double a = H[m * 10] * P[HC[0] * NS + j];
                for (int k = 1; k < 10; ++k) a = a + H[m * 10 + k] * P[HC[k] * NS + j];
                HP[m * NS + j] = a;
            }
        PMat M;
        for (int i = 0; i < NS; ++i)
            for (int j = 0; j < NS; ++j)
                M[i * NS + j] = P[i * NS + j] - (K[i * 3] * HP[j] + K[i * 3 + 1] * HP[NS + j] +
                                                 K[i * 3 + 2] * HP[2 * NS + j]);
        Mat<NS, 3> MHt{};
        for (int i = 0; i < NS; ++i)
            for (int m = 0; m < 3; ++m) {
                double a = M[i * NS + HC[0]] * H[m * 10];
                for (int k = 1; k < 10; ++k) a = a + M[i * NS + HC[k]] * H[m * 10 + k];
                MHt[i * 3 + m] = a;
            }
        for (int i = 0; i < NS; ++i)
            for (int j = 0; j < NS; ++j) {
                const double kr0 = K[i * 3] * r, kr1 = K[i * 3 + 1] * r, kr2 = K[i * 3 + 2] * r;
                P[i * NS + j] = (M[i * NS + j] - (MHt[i * 3] * K[j * 3] + MHt[i * 3 + 1] * K[j * 3 + 1] +
                                                  MHt[i * 3 + 2] * K[j * 3 + 2])) +
                                (kr0 * K[j * 3] + kr1 * K[j * 3 + 1] + kr2 * K[j * 3 + 2]);
            }
        q_new = quat_unit(quat_mul(st.q_P_from_body, quat_from_rotvec({dx[0], dx[1], dx[2]})));
        for (int i = 0; i < NX; ++i) x_new[i] = xh[i] + dx[3 + i];
    }
    const M3 C_BP_new = dcm_T(q_new);
    cap_platform_yaw(P, col2(C_BP_new), p.max_platform_yaw_sigma_rad);
    symmetrise_p(P);

    const State pre = st;  // what _at_rest reads (the previous update's residual)
    st.q_P_from_body = q_new;
    st.x_hat = x_new;
    st.P = P;
    reset_interval(st, C_BP_new);
    st.n_updates = pre.n_updates + 1;
    st.n_rejected = pre.n_rejected + (fused ? 0 : 1);
    st.gated_run = fused ? 0 : pre.gated_run + 1;
    st.reentry_wait = (gate_ok && !fused) ? pre.reentry_wait + 1 : 0;
    st.has_z_prev = true;
    st.z_prev_m_s2 = z;

    dg.fused = fused;
    dg.innovation_m_s2 = z;
    dg.test_ratio = ratio;
    dg.settle_ratio = settle_ratio;
    dg.accel_var_raised_m2_s4 = raised;
    dg.why = fused ? FUSED : (!gate_ok ? GATED_OUT : NOT_SETTLED);
    const V3 f_c{f_mean[0] - xh[12], f_mean[1] - xh[13], f_mean[2] - xh[14]};
    if (!gate_ok && at_rest(pre, f_c, g, w_mean, z, r, q_av, p)) {
        st.rest_gated_run = pre.rest_gated_run + 1;
        st.rest_f_sum_m_s2 = add3(pre.rest_f_sum_m_s2, f_c);
        st.rest_s = pre.rest_s + T;
    } else if (pre.rest_gated_run) {
        st.rest_gated_run = 0;
        st.rest_f_sum_m_s2 = {0.0, 0.0, 0.0};
        st.rest_s = 0.0;
    }
    if (p.relevel_allowed && st.rest_gated_run && st.rest_s + 1e-9 >= p.relevel_rest_s) {
        dg.relevel_rad = relevel(st, p);
        dg.fused = false;
        dg.why = RELEVELLED;
        dg.accel_var_raised_m2_s4 = 0.0;
    }
    return dg;
}

// _levelled_tilt_sigma_rad: init_tilt_sigma_rad, or the levelling window's scatter
// sqrt(tr Cov(f)) / |fm| when larger (at most unseen_max_sigma_rad)
inline double levelled_tilt_sigma(const State& s, const V3& fm, const Params& p) {
    const double n = static_cast<double>(s.acc_n);
    double var = 0.0;
    for (int i = 0; i < 3; ++i) var += std::max(s.acc_f_sq_sum_m2_s4[i] / n - fm[i] * fm[i], 0.0);
    const double g2 = fm[0] * fm[0] + fm[1] * fm[1] + fm[2] * fm[2];
    if (var <= p.init_tilt_sigma_rad * p.init_tilt_sigma_rad * g2) return p.init_tilt_sigma_rad;
    return std::min(std::sqrt(var / g2), p.unseen_max_sigma_rad);
}

// _init_step: the specific force averaged over init_period_s levels the filter
inline Diag init_step(State& s, double time_s, const V3& w, const V3& f, const Params& p) {
    if (!s.has_time) { s.has_time = true; s.time_s = time_s; }
    s.acc_n += 1;
    s.acc_f_sum_m_s2 = add3(s.acc_f_sum_m_s2, f);
    for (int i = 0; i < 3; ++i) s.acc_f_sq_sum_m2_s4[i] += f[i] * f[i];
    Diag d;
    if (time_s - s.time_s + 1e-9 < p.init_period_s) {
        d.code = LEVELLING;
        return d;
    }
    const V3 fm = div3(s.acc_f_sum_m_s2, static_cast<double>(s.acc_n));
    const double roll = std::atan2(-fm[1], -fm[2]);
    const double pitch = std::atan2(fm[0], std::hypot(fm[1], fm[2]));
    const Q4 q = quat_from_euler(roll, pitch, 0.0);
    const M3 C_BP = dcm_T(q);
    State n;
    n.initialised = true;
    n.has_time = true;
    n.time_s = time_s;
    n.q_P_from_body = q;
    n.x_hat = s.x_hat;
    n.P = initial_covariance(C_BP, p, levelled_tilt_sigma(s, fm, p), s.has_bias_prior_sigma, s.bias_prior_sigma_rad_s);
    n.has_gyro_prev = true;
    n.gyro_prev_rad_s = w;
    n.acc_C_BP_start = C_BP;
    n.has_bias_prior_sigma = s.has_bias_prior_sigma;
    n.bias_prior_sigma_rad_s = s.bias_prior_sigma_rad_s;
    s = n;
    d.code = LEVELLED;
    return d;
}

// polar_attitude_step: one IMU sample (body frame); the state changes in place only where the
// reference returns a new state
inline Diag step(State& s, double time_s, const V3& w, const V3& f, const Params& p) {
    Diag d;
    if (!(std::isfinite(time_s) && finite3(w) && finite3(f))) {
        d.code = NON_FINITE;
        return d;
    }
    if (!s.initialised) return init_step(s, time_s, w, f, p);
    if (!s.has_time) {
        s.has_time = true; s.time_s = time_s;
        s.has_gyro_prev = true; s.gyro_prev_rad_s = w;
        d.code = RESTARTED;
        return d;
    }
    const double dt = time_s - s.time_s;
    d.dt_s = dt;
    if (dt <= 0.0) {
        d.code = TIME_NOT_INCREASING;
        return d;
    }
    if (!s.has_gyro_prev) {
        s.time_s = time_s;
        s.has_gyro_prev = true; s.gyro_prev_rad_s = w;
        d.code = RESTARTED;
        return d;
    }
    if (dt > p.max_dt_s) {
        unseen(s, dt, p);
        s.has_time = true; s.time_s = time_s;
        s.has_gyro_prev = true; s.gyro_prev_rad_s = w;
        s.has_sample_dt = false;
        d.code = GAP;
        return d;
    }
    const double span_s = std::min(s.has_sample_dt ? s.sample_dt_s : dt, p.sample_span_max_s);
    const bool hole = dt > 1.5 * span_s;

    const XVec& xh = s.x_hat;
    const V3 b_g{xh[0], xh[1], xh[2]};
    const V3 k_g{1.0 - xh[16], 1.0 - xh[17], 1.0 - xh[18]};
    const V3 W_hat{xh[6] + xh[9], xh[7] + xh[10], xh[8] + xh[11]};
    const V3 wp_b = sub3(s.gyro_prev_rad_s, b_g), w_b = sub3(w, b_g);
    V3 a_prev, a_now;
    for (int i = 0; i < 3; ++i) {
        a_prev[i] = wp_b[i] * k_g[i] * dt;
        a_now[i] = w_b[i] * k_g[i] * dt;
    }
    const V3 coning = div3(cross3(a_prev, a_now), 12.0);
    V3 dtheta;
    double h_s = 0.0;
    if (hole) {
        h_s = dt - span_s;
        for (int i = 0; i < 3; ++i)
            dtheta[i] = (0.5 * (wp_b[i] + w_b[i]) * k_g[i] * h_s + w_b[i] * k_g[i] * span_s) + coning[i];
    } else {
        dtheta = add3(a_now, coning);
    }
    const Q4 qb = quat_from_rotvec(dtheta);
    const Q4 q = quat_unit(quat_mul(quat_from_rotvec(scale3(scale3(W_hat, -1.0), dt)),
                                    quat_mul(s.q_P_from_body, qb)));
    const double decay = std::exp(-dt / p.vehicle_accel_tau_s);
    const Q4 q_int = quat_mul(s.acc_q_b0_from_b, qb);
    if (hole) {
        const double v = bridge_variance(s.gyro_prev_rad_s, w, h_s, p);
        for (int i = 0; i < 3; ++i) s.P[i * NS + i] += v;
    }
    V3 down_mean;
    if (hole) {
        V3 dth_span;
        for (int i = 0; i < 3; ++i) dth_span[i] = w_b[i] * k_g[i] * span_s;
        const Q4 q_s = quat_mul(quat_from_rotvec(scale3(W_hat, span_s)),
                                quat_mul(q, quat_from_rotvec(scale3(dth_span, -1.0))));
        down_mean = down_mean_over_sample(q_s, q, W_hat, span_s, dth_span);
    } else {
        down_mean = down_mean_over_sample(s.q_P_from_body, q, W_hat, dt, dtheta);
    }
    for (int i = 3; i < 6; ++i) s.x_hat[i] *= decay;
    ramp_bias(s.x_hat, dt, p);
    s.time_s = time_s;
    s.q_P_from_body = q;
    s.gyro_prev_rad_s = w;
    s.has_sample_dt = true;
    s.sample_dt_s = hole ? span_s : std::min(dt, p.sample_span_max_s);
    s.acc_n += 1;
    s.acc_dt_s = s.acc_dt_s + dt;
    s.acc_f_sum_m_s2 = add3(s.acc_f_sum_m_s2, f);
    s.acc_down_sum = add3(s.acc_down_sum, down_mean);
    s.acc_q_b0_from_b = q_int;
    if (s.acc_dt_s + 1e-9 < p.update_period_s) return d;  // code SAMPLE
    Diag u = update(s, p);
    u.dt_s = dt;
    return u;
}

// polar_attitude_estimate (for an initialised state): roll, pitch, their 2x2 covariance
inline void estimate(const State& s, double& roll, double& pitch, Mat<2, 2>& cov) {
    const V3 e = euler_from_dcm(dcm_from_quat(s.q_P_from_body));
    roll = e[0];
    pitch = e[1];
    // roll_pitch_jacobian
    const V3 d = down_in_body(s.q_P_from_body);
    const M3 Dd = skew(d);
    const double den = std::pow(d[1], 2) + std::pow(d[2], 2);
    const double sq = std::sqrt(std::max(1e-12, den));  // 1 - d_x^2 without its cancellation
    Mat<2, 3> J{};
    for (int j = 0; j < 3; ++j) {
        J[j] = (d[2] * Dd[3 + j] - d[1] * Dd[6 + j]) / den;
        J[3 + j] = -Dd[j] / sq;
    }
    cov = mm<2, 3, 2>(mm<2, 3, 3>(J, att_block(s.P)), tr<2, 3>(J));
}

}  // namespace polar
}  // namespace azimuthd
