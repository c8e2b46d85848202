// KF2: method B's 9-state closed-loop error filter (the compiled twin of estimators/ahrs_kf2.py,
// which stays the reference and holds the derivation: METHODS.md B2, seed eq. 17-37).
// Error states x = [gamma (3), db_g (3), dbeta (3)]; Phi = I + A dt + (A dt)^2 / 2 over the
// covariance period; every update gated per component, then fed back (q <- q q(gamma),
// b <- b + db_g, beta <- beta + dbeta). The Kalman mechanics are filterpy's KalmanFilter (predict;
// update with the Joseph form), written out here in the same operation order.
#pragma once

#include "ahrs_math.hpp"

namespace azimuthd {

constexpr int KN = 9;
using P9 = Mat<KN, KN>;
constexpr int NC = 10;  // consider parameters: the soft iron (9, KF1's order), the declination error
using S9 = Mat<KN, NC>;

struct Kf2Params {
    double gyro_noise_rad_s_rthz, gyro_scale_sigma, gyro_scale_corr_s, gyro_bias_sigma_rad_s, gyro_bias_tau_s;
    double mag_bias_sigma, mag_bias_tau_s, mag_sigma, mag_gate_sigma, mag_norm_tolerance, max_mag_rate_rad_s;
    double air_gate_sigma, ref_gate_sigma, ref_reset_rad, cov_period_s, max_dt_s;
    double unseen_tilt_rate_sigma_rad_s, unseen_tilt_max_sigma_rad, unseen_heading_rate_sigma_rad_s,
        unseen_heading_max_sigma_rad;
    double sigma_att_init_rad, sigma_heading_init_rad, sigma_gyro_bias_init_rad_s, sigma_mag_bias_init;
};

struct Kf2 {
    Q4 q_nav_from_body{1, 0, 0, 0};
    V3 gyro_bias_rad_s{0, 0, 0};
    V3 mag_bias{0, 0, 0};
    P9 P{};
    bool has_time = false;            // time_s, omega_prev_rad_s, cov_time_s, acc_angle_rad: None or set
    double time_s = 0.0;
    bool has_omega_prev = false;
    V3 omega_prev_rad_s{0, 0, 0};
    bool has_cov_time = false;
    double cov_time_s = 0.0;
    bool has_acc_angle = false;
    V3 acc_angle_rad{0, 0, 0};
    double acc_omega_sq = 0.0;
    long n_mag_fused = 0, n_mag_rejected = 0, n_mag_gated = 0, n_air_fused = 0, n_air_rejected = 0,
         n_ref_fused = 0, n_ref_rejected = 0, n_resets = 0;
    bool has_S = false;  // consider_sens: None (zero) or S = d(error)/d(consider parameters)
    S9 S{};
};

// Kf2Diag.reason, as a code (what the synthetic AHRS reads of it)
enum class Kf2Code { ok, first_sample, non_finite, time_not_increasing, gap, gate, reset_to_reference,
                     mag_non_finite, mag_disturbance, rate_gate, weak_horizontal };

struct Kf2Diag {
    bool fused;
    Kf2Code code;
};

// body-frame gamma covariance for roll/pitch and heading sigmas: gamma = W d_euler
inline M3 gamma_cov_from_euler_sigmas(const Q4& q, double sigma_tilt, double sigma_heading) {
    const V3 e = euler_from_dcm(dcm_from_quat(q));
    const M3 W = body_rate_matrix(e[0], e[1]);
    const M3 D{std::pow(sigma_tilt, 2), 0, 0, 0, std::pow(sigma_tilt, 2), 0, 0, 0, std::pow(sigma_heading, 2)};
    return mm<3, 3, 3>(mm<3, 3, 3>(W, D), tr<3, 3>(W));
}

inline void set_block3(P9& P, int r0, int c0, const M3& B) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) P[(r0 + i) * KN + c0 + j] = B[i * 3 + j];
}
inline M3 block3(const P9& P, int r0, int c0) {
    M3 B{};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) B[i * 3 + j] = P[(r0 + i) * KN + c0 + j];
    return B;
}

inline Kf2 kf2_init(const Q4& q_in, const Kf2Params& p, double sigma_tilt, double sigma_heading) {
    Kf2 s;
    const double n = std::sqrt(dot4(q_in));
    s.q_nav_from_body = {q_in[0] / n, q_in[1] / n, q_in[2] / n, q_in[3] / n};
    s.P.fill(0.0);
    set_block3(s.P, 0, 0, gamma_cov_from_euler_sigmas(s.q_nav_from_body, sigma_tilt, sigma_heading));
    for (int i = 3; i < 6; ++i) s.P[i * KN + i] = 1.0 * std::pow(p.sigma_gyro_bias_init_rad_s, 2);
    for (int i = 6; i < 9; ++i) s.P[i * KN + i] = 1.0 * std::pow(p.sigma_mag_bias_init, 2);
    return s;
}

// (roll, pitch, heading) and their covariance T P_gamma T^T
inline void kf2_euler_and_cov(const Kf2& s, V3& e, M3& cov) {
    e = euler_from_dcm(dcm_from_quat(s.q_nav_from_body));
    const M3 T = euler_rate_matrix_reported(e[0], e[1]);
    cov = mm<3, 3, 3>(mm<3, 3, 3>(T, block3(s.P, 0, 0)), tr<3, 3>(T));
}

inline double kf2_heading_var(const Kf2& s) {
    V3 e;
    M3 cov;
    kf2_euler_and_cov(s, e, cov);
    return cov[8];
}

// P over the accumulated interval: Phi = I + A dt + (A dt)^2 / 2, Q diagonal (filterpy predict)
inline void kf2_propagate(Kf2& s, const Kf2Params& p) {
    if (!s.has_cov_time || !s.has_time || !s.has_acc_angle) return;
    const double dt = s.time_s - s.cov_time_s;
    if (dt <= 0.0) return;
    const V3 w_mean{s.acc_angle_rad[0] / dt, s.acc_angle_rad[1] / dt, s.acc_angle_rad[2] / dt};
    P9 A{};
    const M3 sk = skew(w_mean);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) A[i * KN + j] = -sk[i * 3 + j];
    for (int i = 0; i < 3; ++i) {
        A[i * KN + 3 + i] = -1.0;
        A[(3 + i) * KN + 3 + i] = -1.0 / p.gyro_bias_tau_s;
        A[(6 + i) * KN + 6 + i] = -1.0 / p.mag_bias_tau_s;
    }
    P9 Ad, half;
    for (int i = 0; i < KN * KN; ++i) Ad[i] = A[i] * dt;
    for (int i = 0; i < KN * KN; ++i) half[i] = 0.5 * Ad[i];
    const P9 AA = mm<KN, KN, KN>(half, Ad);
    const P9 I = eye<KN>();
    P9 Phi;
    for (int i = 0; i < KN * KN; ++i) Phi[i] = (I[i] + Ad[i]) + AA[i];
    const double q_g = std::pow(p.gyro_noise_rad_s_rthz, 2) * dt +
                       (std::pow(p.gyro_scale_sigma, 2) * p.gyro_scale_corr_s * s.acc_omega_sq);
    const double q_b = 2.0 * std::pow(p.gyro_bias_sigma_rad_s, 2) / p.gyro_bias_tau_s * dt;
    const double q_m = 2.0 * std::pow(p.mag_bias_sigma, 2) / p.mag_bias_tau_s * dt;
    P9 P = mm<KN, KN, KN>(mm<KN, KN, KN>(Phi, s.P), tr<KN, KN>(Phi));
    for (int i = 0; i < KN * KN; ++i) P[i] = 1.0 * P[i];
    for (int i = 0; i < 3; ++i) {
        P[i * KN + i] += q_g;
        P[(3 + i) * KN + 3 + i] += q_b;
        P[(6 + i) * KN + 6 + i] += q_m;
    }
    symmetrise<KN>(P);
    s.P = P;
    if (s.has_S) s.S = mm<KN, KN, NC>(Phi, s.S);  // S <- Phi S
    s.cov_time_s = s.time_s;
    s.acc_angle_rad = {0.0, 0.0, 0.0};
    s.has_acc_angle = true;
    s.acc_omega_sq = 0.0;
}

// unseen_s without IMU samples: P_gamma += W diag(s_t^2, s_t^2, s_h^2) W^T + (sigma_bg unseen)^2 I,
// the Markov states relax (ahrs_kf2.kf2_unseen)
inline void kf2_unseen(Kf2& s, double unseen_s, const Kf2Params& p) {
    if (!(std::isfinite(unseen_s) && unseen_s >= 0.0))
        throw std::invalid_argument("unseen_s must be finite and >= 0, got " + py_repr(unseen_s));
    const double s_t = std::min(p.unseen_tilt_rate_sigma_rad_s * unseen_s, p.unseen_tilt_max_sigma_rad);
    const double s_h = std::min(p.unseen_heading_rate_sigma_rad_s * unseen_s, p.unseen_heading_max_sigma_rad);
    double a[KN];
    for (int i = 0; i < KN; ++i) a[i] = 1.0;
    const double ab = std::exp(-unseen_s / p.gyro_bias_tau_s), am = std::exp(-unseen_s / p.mag_bias_tau_s);
    for (int i = 3; i < 6; ++i) a[i] = ab;
    for (int i = 6; i < 9; ++i) a[i] = am;
    P9 P;
    for (int i = 0; i < KN; ++i)
        for (int j = 0; j < KN; ++j) P[i * KN + j] = a[i] * s.P[i * KN + j] * a[j];
    const double vb = 1.0 * (1.0 - std::pow(ab, 2)) * std::pow(p.gyro_bias_sigma_rad_s, 2);
    const double vm = 1.0 * (1.0 - std::pow(am, 2)) * std::pow(p.mag_bias_sigma, 2);
    for (int i = 3; i < 6; ++i) P[i * KN + i] += vb;
    for (int i = 6; i < 9; ++i) P[i * KN + i] += vm;
    const M3 G = gamma_cov_from_euler_sigmas(s.q_nav_from_body, s_t, s_h);
    const double vg = 1.0 * std::pow(p.gyro_bias_sigma_rad_s * unseen_s, 2);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) P[i * KN + j] += G[i * 3 + j] + (i == j ? vg : 0.0);
    symmetrise<KN>(P);
    s.P = P;
    if (s.has_S)
        for (int i = 0; i < KN; ++i)
            for (int j = 0; j < NC; ++j) s.S[i * NC + j] = a[i] * s.S[i * NC + j];
}

// One IMU sample (body rate, rad/s): the attitude every sample, P every cov_period_s.
inline Kf2Diag kf2_predict(Kf2& s, const V3& gyro_body, double time_s, const Kf2Params& p, double& dt_out) {
    const V3 w{gyro_body[0] - s.gyro_bias_rad_s[0], gyro_body[1] - s.gyro_bias_rad_s[1],
               gyro_body[2] - s.gyro_bias_rad_s[2]};
    dt_out = 0.0;
    if (!finite3(w) || !std::isfinite(time_s)) return {false, Kf2Code::non_finite};
    if (!s.has_time || !s.has_omega_prev) {
        s.has_time = true; s.time_s = time_s;
        s.has_omega_prev = true; s.omega_prev_rad_s = w;
        s.has_cov_time = true; s.cov_time_s = time_s;
        s.has_acc_angle = true; s.acc_angle_rad = {0.0, 0.0, 0.0};
        s.acc_omega_sq = 0.0;
        return {false, Kf2Code::first_sample};
    }
    const double dt = time_s - s.time_s;
    dt_out = dt;
    if (dt <= 0.0) return {false, Kf2Code::time_not_increasing};
    if (dt > p.max_dt_s) {
        // a gap: the attitude kept, its covariance grown for the part beyond max_dt_s
        kf2_propagate(s, p);
        kf2_unseen(s, dt - p.max_dt_s, p);
        s.time_s = time_s;
        s.omega_prev_rad_s = w; s.has_omega_prev = true;
        s.cov_time_s = time_s; s.has_cov_time = true;
        s.acc_angle_rad = {0.0, 0.0, 0.0}; s.has_acc_angle = true;
        s.acc_omega_sq = 0.0;
        return {false, Kf2Code::gap};
    }
    const V3 dth{0.5 * (s.omega_prev_rad_s[0] + w[0]) * dt, 0.5 * (s.omega_prev_rad_s[1] + w[1]) * dt,
                 0.5 * (s.omega_prev_rad_s[2] + w[2]) * dt};
    const Q4 q = quat_unit(quat_mul(s.q_nav_from_body, quat_from_rotvec(dth)));
    const double cov_time_before = s.cov_time_s;
    s.q_nav_from_body = q;
    s.time_s = time_s;
    s.omega_prev_rad_s = w;
    s.acc_angle_rad = {s.acc_angle_rad[0] + dth[0], s.acc_angle_rad[1] + dth[1], s.acc_angle_rad[2] + dth[2]};
    s.acc_omega_sq = s.acc_omega_sq + (dth[0] * dth[0] + dth[1] * dth[1] + dth[2] * dth[2]) / dt;
    if (time_s - cov_time_before >= p.cov_period_s - 1e-9) kf2_propagate(s, p);
    return {true, Kf2Code::ok};
}

// Gated update + closed-loop feedback (ahrs_kf2._update; filterpy's update with x = 0).
template <int M>
inline Kf2Diag kf2_update(Kf2& s, const std::array<double, M>& z, const Mat<M, KN>& H, const Mat<M, M>& R,
                          double n_gate, const Kf2Params& p, const Mat<M, NC>* D = nullptr) {
    kf2_propagate(s, p);
    const Mat<KN, M> Ht = tr<M, KN>(H);
    Mat<M, M> S = mm<M, KN, M>(mm<M, KN, KN>(H, s.P), Ht);
    for (int i = 0; i < M * M; ++i) S[i] = S[i] + R[i];
    double ratio = 0.0;
    for (int i = 0; i < M; ++i) {
        const double r = std::fabs(z[i]) / (n_gate * std::sqrt(S[i * M + i]));
        if (i == 0 || r > ratio) ratio = r;
    }
    if (ratio > 1.0) return {false, Kf2Code::gate};
    const Mat<KN, M> PHT = mm<KN, KN, M>(s.P, Ht);
    Mat<M, M> S2 = mm<M, KN, M>(H, PHT);
    for (int i = 0; i < M * M; ++i) S2[i] = S2[i] + R[i];
    const Mat<KN, M> K = mm<KN, M, M>(PHT, inv<M>(S2));
    const std::array<double, KN> dx = mv<KN, M>(K, z);
    P9 I_KH = mm<KN, M, KN>(K, H);
    const P9 I = eye<KN>();
    for (int i = 0; i < KN * KN; ++i) I_KH[i] = I[i] - I_KH[i];
    if (s.has_S || D) {  // the consider sensitivity: S <- (I - K H) S - K D
        S9 Sn = s.has_S ? mm<KN, KN, NC>(I_KH, s.S) : S9{};
        if (D) {
            const S9 KD = mm<KN, M, NC>(K, *D);
            for (int i = 0; i < KN * NC; ++i) Sn[i] = Sn[i] - KD[i];
        }
        s.S = Sn;
        s.has_S = true;
    }
    P9 P = mm<KN, KN, KN>(mm<KN, KN, KN>(I_KH, s.P), tr<KN, KN>(I_KH));
    const P9 KRK = mm<KN, M, KN>(mm<KN, M, M>(K, R), tr<KN, M>(K));
    for (int i = 0; i < KN * KN; ++i) P[i] = P[i] + KRK[i];
    s.q_nav_from_body = quat_unit(quat_mul(s.q_nav_from_body, quat_from_rotvec({dx[0], dx[1], dx[2]})));
    for (int i = 0; i < 3; ++i) {
        s.gyro_bias_rad_s[i] = s.gyro_bias_rad_s[i] + dx[3 + i];
        s.mag_bias[i] = s.mag_bias[i] + dx[6 + i];
    }
    symmetrise<KN>(P);
    s.P = P;
    return {true, Kf2Code::ok};
}

// the gates both magnetometer updates share (a field magnitude off the model's, a rate too high)
inline bool kf2_mag_gated(Kf2& s, const V3& m_n, const Kf2Params& p, Kf2Diag& d) {
    if (std::fabs(norm3(m_n) - 1.0) > p.mag_norm_tolerance) {
        s.n_mag_rejected += 1;
        d = {false, Kf2Code::mag_disturbance};
        return true;
    }
    if (s.has_omega_prev && norm3(s.omega_prev_rad_s) > p.max_mag_rate_rad_s) {
        s.n_mag_rejected += 1;
        d = {false, Kf2Code::rate_gate};
        return true;
    }
    return false;
}

// the soft iron's columns of KF1's D(B) (mag_error_kf.error_jacobian[:, 3:12]) at the body field b
inline Mat<3, 9> kf2_soft_iron_jacobian(const V3& b) {
    Mat<3, 9> D{};
    D[0 * 9 + 0] = b[0]; D[1 * 9 + 1] = b[1]; D[2 * 9 + 2] = b[2];
    D[0 * 9 + 3] = b[1]; D[0 * 9 + 4] = b[2];
    D[1 * 9 + 5] = b[0]; D[1 * 9 + 6] = b[2];
    D[2 * 9 + 7] = b[0]; D[2 * 9 + 8] = b[1];
    return D;
}

inline void kf2_count_mag(Kf2& s, const Kf2Diag& d) {
    if (d.fused) s.n_mag_fused += 1;
    else { s.n_mag_rejected += 1; s.n_mag_gated += 1; }
}

// Magnetometer update (eq. 21): z = m - C^T B_n - beta = [b0 x] gamma + dbeta
inline Kf2Diag kf2_update_mag(Kf2& s, const V3& m, const V3& Bn, const Kf2Params& p) {
    if (!finite3(m) || !finite3(Bn)) return {false, Kf2Code::mag_non_finite};
    const double norm = norm3(Bn);
    if (!(norm > 0.0)) throw std::invalid_argument("field_nav_gauss must be non-zero");
    const V3 m_n{m[0] / norm, m[1] / norm, m[2] / norm};
    Kf2Diag d{false, Kf2Code::ok};
    if (kf2_mag_gated(s, m_n, p, d)) return d;
    const M3 C = dcm_from_quat(s.q_nav_from_body);
    const V3 b0 = mv<3, 3>(tr<3, 3>(C), V3{Bn[0] / norm, Bn[1] / norm, Bn[2] / norm});
    const V3 z{m_n[0] - b0[0] - s.mag_bias[0], m_n[1] - b0[1] - s.mag_bias[1], m_n[2] - b0[2] - s.mag_bias[2]};
    Mat<3, KN> H{};
    const M3 sk = skew(b0);
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) H[i * KN + j] = sk[i * 3 + j];
        H[i * KN + 6 + i] = 1.0;
    }
    const double r = std::pow(p.mag_sigma, 2);
    const M3 R{r * 1.0, 0, 0, 0, r * 1.0, 0, 0, 0, r * 1.0};
    // D_c: the soft iron at b0 and the declination turning the model field about down
    Mat<3, NC> D{};
    const Mat<3, 9> Ds = kf2_soft_iron_jacobian(b0);
    const V3 dB = mv<3, 3>(tr<3, 3>(C), V3{-(Bn[1] / norm), Bn[0] / norm, 0.0});
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 9; ++j) D[i * NC + j] = Ds[i * 9 + j];
        D[i * NC + 9] = dB[i];
    }
    d = kf2_update<3>(s, z, H, R, p.mag_gate_sigma, p, &D);
    kf2_count_mag(s, d);
    return d;
}

// Magnetometer as a heading-only measurement (ahrs_kf2.kf2_update_mag_heading)
inline Kf2Diag kf2_update_mag_heading(Kf2& s, const V3& m, const V3& Bn, const Kf2Params& p) {
    if (!finite3(m) || !finite3(Bn)) return {false, Kf2Code::mag_non_finite};
    const double norm = norm3(Bn);
    if (!(norm > 0.0)) throw std::invalid_argument("field_nav_gauss must be non-zero");
    const double bh = std::hypot(Bn[0], Bn[1]) / norm;
    if (!(bh > 0.05)) return {false, Kf2Code::weak_horizontal};
    const V3 m_n{m[0] / norm, m[1] / norm, m[2] / norm};
    Kf2Diag d{false, Kf2Code::ok};
    if (kf2_mag_gated(s, m_n, p, d)) return d;
    const M3 C = dcm_from_quat(s.q_nav_from_body);
    const V3 e = euler_from_dcm(C);
    const V3 mh = mv<3, 3>(C, V3{m_n[0] - s.mag_bias[0], m_n[1] - s.mag_bias[1], m_n[2] - s.mag_bias[2]});
    const double x = mh[0], y = mh[1];
    const double r2 = x * x + y * y;
    const std::array<double, 1> z{wrap_pi(std::atan2(Bn[1], Bn[0]) - std::atan2(y, x))};
    Mat<1, KN> H{};
    const M3 T = euler_rate_matrix(e[0], e[1]);
    for (int j = 0; j < 3; ++j) {
        H[j] = T[6 + j];
        H[6 + j] = -(x * C[3 + j] - y * C[j]) / r2;
    }
    const Mat<1, 1> R{std::pow(p.mag_sigma / bh, 2)};
    // D = dz/dm D(b0) for the soft iron (dz/dm: H's dbeta columns), -1 for the declination
    const Mat<3, 9> Ds = kf2_soft_iron_jacobian(mv<3, 3>(tr<3, 3>(C), V3{Bn[0] / norm, Bn[1] / norm, Bn[2] / norm}));
    Mat<1, NC> D{};
    for (int j = 0; j < 9; ++j) D[j] = (H[6] * Ds[j] + H[7] * Ds[9 + j]) + H[8] * Ds[18 + j];
    D[9] = -1.0;
    d = kf2_update<1>(s, z, H, R, p.mag_gate_sigma, p, &D);
    kf2_count_mag(s, d);
    return d;
}

// Air-data roll/pitch update (eq. 22, 24-25, 35-37); turn_gain_s = d phi_ref / d psi_dot
inline Kf2Diag kf2_update_air(Kf2& s, double roll_ref, double pitch_ref, double sigma_roll, double sigma_pitch,
                              double turn_gain_s, const Kf2Params& p) {
    const M3 C = dcm_from_quat(s.q_nav_from_body);
    const V3 e = euler_from_dcm(C);
    const double roll = e[0], pitch = e[1];
    const M3 T = euler_rate_matrix(roll, pitch);
    const std::array<double, 2> z{wrap_pi(roll_ref - roll), pitch_ref - pitch};
    Mat<2, KN> H{};
    for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 3; ++j) H[i * KN + j] = T[i * 3 + j];
    const double sphi = std::sin(roll), cphi = std::cos(roll), cth = std::cos(pitch);
    H[4] = turn_gain_s * sphi / cth;
    H[5] = turn_gain_s * cphi / cth;
    const Mat<2, 2> R{std::pow(sigma_roll, 2), 0.0, 0.0, std::pow(sigma_pitch, 2)};
    const Kf2Diag d = kf2_update<2>(s, z, H, R, p.air_gate_sigma, p);
    if (d.fused) s.n_air_fused += 1;
    else s.n_air_rejected += 1;
    return d;
}

// Trusted reference attitude (the FC's ATTITUDE): z = euler_ref - euler_hat, our attitude carried
// back to the reference's time; a residual beyond ref_reset_rad re-initialises the attitude.
inline Kf2Diag kf2_update_reference(Kf2& s, const V3& e_ref, double time_ref_s, double sigma_tilt, double sigma_yaw,
                                    const Kf2Params& p, bool use_yaw) {
    Q4 q = s.q_nav_from_body;
    const bool back = s.has_time && s.has_omega_prev;
    const double lag = back ? s.time_s - time_ref_s : 0.0;
    if (back)
        q = quat_mul(q, quat_from_rotvec({-s.omega_prev_rad_s[0] * lag, -s.omega_prev_rad_s[1] * lag,
                                          -s.omega_prev_rad_s[2] * lag}));
    const V3 ours = euler_from_dcm(dcm_from_quat(q));
    const double roll = ours[0], pitch = ours[1], yaw = ours[2];
    V3 e = e_ref;
    const V3 z{wrap_pi(e[0] - roll), e[1] - pitch, wrap_pi(e[2] - yaw)};
    const int n = use_yaw ? 3 : 2;
    if (!use_yaw) e = {e[0], e[1], yaw};
    double zmax = std::fabs(z[0]);
    for (int i = 1; i < n; ++i) zmax = std::max(zmax, std::fabs(z[i]));
    if (zmax > p.ref_reset_rad) {
        Q4 q_ref = quat_from_euler(e[0], e[1], e[2]);
        if (back)
            q_ref = quat_mul(q_ref, quat_from_rotvec({s.omega_prev_rad_s[0] * lag, s.omega_prev_rad_s[1] * lag,
                                                     s.omega_prev_rad_s[2] * lag}));
        const double sh = use_yaw ? sigma_yaw : std::sqrt(kf2_heading_var(s));
        P9 P = s.P;
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < KN; ++j) { P[i * KN + j] = 0.0; P[j * KN + i] = 0.0; }
        set_block3(P, 0, 0, gamma_cov_from_euler_sigmas(q_ref, sigma_tilt, sh));
        s.q_nav_from_body = quat_unit(q_ref);
        s.P = P;
        if (s.has_S && use_yaw)  // the attitude is the reference's now
            for (int i = 0; i < 3 * NC; ++i) s.S[i] = 0.0;
        s.n_resets += 1;
        return {true, Kf2Code::reset_to_reference};
    }
    const M3 T = euler_rate_matrix(roll, pitch);
    const double vt = std::pow(sigma_tilt, 2), vy = std::pow(sigma_yaw, 2);
    Kf2Diag d;
    if (use_yaw) {
        Mat<3, KN> H{};
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) H[i * KN + j] = T[i * 3 + j];
        d = kf2_update<3>(s, z, H, M3{vt, 0, 0, 0, vt, 0, 0, 0, vy}, p.ref_gate_sigma, p);
    } else {
        Mat<2, KN> H{};
        for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 3; ++j) H[i * KN + j] = T[i * 3 + j];
        d = kf2_update<2>(s, std::array<double, 2>{z[0], z[1]}, H, Mat<2, 2>{vt, 0, 0, vt}, p.ref_gate_sigma, p);
    }
    if (d.fused) s.n_ref_fused += 1;
    else s.n_ref_rejected += 1;
    return d;
}

}  // namespace azimuthd
