// KF1: the magnetometer error filter (the compiled twin of estimators/mag_error_kf.py, which stays
// the reference and holds the derivation: METHODS.md B2 "KF1", seed eq. 9-16). 12 random-walk
// states x = [b (3), s (3), k_xy k_xz k_yx k_yz k_zx k_zy], fields normalised by |B_model|;
// z = C B_meas / |B| - B_nav / |B| = C D(B) x + e, gated on y^T S^-1 y.
#pragma once

#include "ahrs_math.hpp"

namespace azimuthd {

constexpr int K1 = 12;

struct Kf1Params {
    double sigma_rw_per_sqrt_s, sigma_meas, chi2_gate, max_rate_rad_s, min_update_interval_s;
};

struct Kf1 {
    std::array<double, K1> x{};
    Mat<K1, K1> P{};
    bool has_norm = false;
    double field_norm_gauss = 0.0;
    bool has_time = false;
    double time_s = 0.0;
    long n_updates = 0, n_rejected_chi2 = 0, n_rejected_rate = 0;
};

enum class Kf1Code { fused, decimated, rate_gate, chi2_gate };

// D(B) = d(dB)/dx (3 x 12) at the body field B (eq. 13)
inline Mat<3, K1> kf1_error_jacobian(const V3& B) {
    Mat<3, K1> D{};
    for (int i = 0; i < 3; ++i) D[i * K1 + i] = 1.0;
    D[0 * K1 + 3] = B[0]; D[1 * K1 + 4] = B[1]; D[2 * K1 + 5] = B[2];
    D[0 * K1 + 6] = B[1]; D[0 * K1 + 7] = B[2];
    D[1 * K1 + 8] = B[0]; D[1 * K1 + 9] = B[2];
    D[2 * K1 + 10] = B[0]; D[2 * K1 + 11] = B[1];
    return D;
}

// corrected body field (gauss): B = M^-1 (B_meas - b |B_model|), M = I + diag(s) + K
inline V3 kf1_correct_mag(const Kf1& s, const V3& m) {
    const auto& x = s.x;
    const M3 M{1.0 + x[3], x[6], x[7], x[8], 1.0 + x[4], x[9], x[10], x[11], 1.0 + x[5]};
    const double n = s.field_norm_gauss;
    return solve<3>(M, V3{m[0] - x[0] * n, m[1] - x[1] * n, m[2] - x[2] * n});
}

inline Kf1Code kf1_step(Kf1& s, const V3& m, const M3& C, const V3& Bn, const V3& w, double time_s, const Kf1Params& p) {
    if (!(finite3(m) && finite3(Bn) && finite3(w) && std::isfinite(time_s)))
        throw std::invalid_argument("kf1_step: non-finite input");
    const double norm = norm3(Bn);
    if (!(norm > 0.0)) throw std::invalid_argument("field_nav_gauss must be non-zero");
    double dt = 0.0;
    if (s.has_time) {
        dt = time_s - s.time_s;
        if (dt < p.min_update_interval_s - 1e-6) return Kf1Code::decimated;
    }
    if (norm3(w) > p.max_rate_rad_s) {
        s.n_rejected_rate += 1;
        return Kf1Code::rate_gate;
    }
    const V3 Bn_n{Bn[0] / norm, Bn[1] / norm, Bn[2] / norm};
    const V3 B_body = mv<3, 3>(tr<3, 3>(C), Bn_n);
    const V3 Cm = mv<3, 3>(C, V3{m[0] / norm, m[1] / norm, m[2] / norm});
    const V3 z{Cm[0] - Bn_n[0], Cm[1] - Bn_n[1], Cm[2] - Bn_n[2]};
    const Mat<3, K1> H = mm<3, 3, K1>(C, kf1_error_jacobian(B_body));
    const double r = std::pow(p.sigma_meas, 2);
    const M3 R{r * 1.0, 0, 0, 0, r * 1.0, 0, 0, 0, r * 1.0};
    // predict: F = I (x and P unchanged by it), Q = sigma_rw^2 dt I
    const double q = std::pow(p.sigma_rw_per_sqrt_s, 2) * dt;
    for (int i = 0; i < K1; ++i) s.P[i * K1 + i] = s.P[i * K1 + i] + q * 1.0;
    const Mat<K1, 3> Ht = tr<3, K1>(H);
    const V3 Hx = mv<3, K1>(H, s.x);
    const V3 y{z[0] - Hx[0], z[1] - Hx[1], z[2] - Hx[2]};
    M3 S = mm<3, K1, 3>(mm<3, K1, K1>(H, s.P), Ht);
    for (int i = 0; i < 9; ++i) S[i] = S[i] + R[i];
    const V3 Sy = solve<3>(S, y);
    const double d2 = y[0] * Sy[0] + y[1] * Sy[1] + y[2] * Sy[2];
    s.has_time = true;
    s.time_s = time_s;
    if (!s.has_norm) { s.has_norm = true; s.field_norm_gauss = norm; }
    if (d2 / p.chi2_gate > 1.0) {
        s.n_rejected_chi2 += 1;
        return Kf1Code::chi2_gate;
    }
    // filterpy update, Joseph form
    const Mat<K1, 3> PHT = mm<K1, K1, 3>(s.P, Ht);
    M3 S2 = mm<3, K1, 3>(H, PHT);
    for (int i = 0; i < 9; ++i) S2[i] = S2[i] + R[i];
    const Mat<K1, 3> K = mm<K1, 3, 3>(PHT, inv<3>(S2));
    const std::array<double, K1> Ky = mv<K1, 3>(K, y);
    for (int i = 0; i < K1; ++i) s.x[i] = s.x[i] + Ky[i];
    Mat<K1, K1> I_KH = mm<K1, 3, K1>(K, H);
    const Mat<K1, K1> I = eye<K1>();
    for (int i = 0; i < K1 * K1; ++i) I_KH[i] = I[i] - I_KH[i];
    Mat<K1, K1> P = mm<K1, K1, K1>(mm<K1, K1, K1>(I_KH, s.P), tr<K1, K1>(I_KH));
    const Mat<K1, K1> KRK = mm<K1, 3, K1>(mm<K1, 3, 3>(K, R), tr<K1, 3>(K));
    for (int i = 0; i < K1 * K1; ++i) P[i] = P[i] + KRK[i];
    symmetrise<K1>(P);
    s.P = P;
    s.n_updates += 1;
    return Kf1Code::fused;
}

}  // namespace azimuthd
