// Method A's per-sample output, the numbers (METHODS.md A step 5; estimators/azimuth.py
// azimuth_output_numbers, which stays the reference): the propagated attitude corrected by the solution's
// estimated errors and rotated into the navigation frame, with the sigmas.
//     C_ISF<-SF' = (I - [G c_g]x) C_ISF<-SF                  (the fit's gyro errors, alpha = G c_g)
//     C_NF<-SF   = R3(psi)^T C_AF<-ISF' C_ISF<-SF'           (unsolved: C_ISF<-AF^T C_ISF<-SF)
//     roll, pitch, q of C_NF<-body = C_NF<-SF C_SF<-body
//     heading / azimuth of u: direction_azimuth_and_sigma (estimators/azimuth_fit.py), with
//     var += field model + wander + (sigma_b (t - t_last sample))^2 (the in-run bias term)
// What stays fixed between two solves (the solution, the flight direction, the mount) is an
// AzimuthOutputCfg, set once per held run; G and C_ISF<-SF are the sample's.
#pragma once

#include <cmath>
#include <limits>
#include <vector>

#include "ahrs_math.hpp"

namespace azimuthd {

struct AzimuthOutputCfg {
    bool set = false;
    bool has_solution = false;
    M3 C_isf_af{};                  // AzimuthState.C_isf_af (the unsolved attitude)
    M3 C_sf_body{};                 // C_body_from_sensor^T
    // the solution (has_solution)
    M3 C_nf_af{}, C_af_isf{};
    double c_gyro[12] = {};
    std::vector<double> P;          // P_psi_c, n x n, n = 1 + 12 + 2
    int nP = 0;
    double arw2 = 0.0;              // gyro_arw_rad_sqrt_s ** 2
    double launch_time_s = 0.0;
    double fm2 = 0.0;               // field_model_sigma_rad ** 2 + wander_var_rad2
    double last_sample_s = NAN;     // Solution.last_sample_s (NaN: no gap term)
    double sigma_b = 0.0;           // gyro_bias_sigma_rad_s
    bool has_u = false;             // u_sf known
    V3 u_sf{};
    bool aligned = false;           // u_sf is the body x axis (array_equal in the reference)
    bool has_du = false;            // du_dbeta_sf (3 x 2, row-major)
    double du[6] = {};
    double c_tilt[2] = {};          // fit.c_hat[12:14]
};

struct AzimuthOutputNumbers {
    double roll = NAN, pitch = NAN;
    Q4 q{1, 0, 0, 0};
    double heading = NAN, heading_sigma = NAN, azimuth = NAN, azimuth_sigma = NAN, launch_azimuth = NAN;
};

// estimators/rotations.py quat_from_dcm (Shepperd; the first maximum, as the reference)
inline Q4 quat_from_dcm(const M3& C) {
    const double c00 = C[0], c01 = C[1], c02 = C[2], c10 = C[3], c11 = C[4], c12 = C[5], c20 = C[6], c21 = C[7],
                 c22 = C[8];
    const double tr_ = c00 + c11 + c22;
    const double cand[4] = {tr_, c00, c11, c22};
    int k = 0;
    for (int i = 1; i < 4; ++i)
        if (cand[i] > cand[k]) k = i;
    Q4 q;
    if (k == 0) {
        const double s = 2.0 * std::sqrt(1.0 + tr_);
        q = {0.25 * s, (c21 - c12) / s, (c02 - c20) / s, (c10 - c01) / s};
    } else if (k == 1) {
        const double s = 2.0 * std::sqrt(1.0 + c00 - c11 - c22);
        q = {(c21 - c12) / s, 0.25 * s, (c01 + c10) / s, (c02 + c20) / s};
    } else if (k == 2) {
        const double s = 2.0 * std::sqrt(1.0 - c00 + c11 - c22);
        q = {(c02 - c20) / s, (c01 + c10) / s, 0.25 * s, (c12 + c21) / s};
    } else {
        const double s = 2.0 * std::sqrt(1.0 - c00 - c11 + c22);
        q = {(c10 - c01) / s, (c02 + c20) / s, (c12 + c21) / s, 0.25 * s};
    }
    return quat_normalize(q);
}

inline V3 cross3(const V3& a, const V3& b) {
    return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}

// a^T M (row vector times matrix)
inline V3 vm3(const V3& a, const M3& M) {
    return {a[0] * M[0] + a[1] * M[3] + a[2] * M[6], a[0] * M[1] + a[1] * M[4] + a[2] * M[7],
            a[0] * M[2] + a[1] * M[5] + a[2] * M[8]};
}

inline double azimuth_of_ned(const V3& v) { return wrap_2pi(std::atan2(v[1], v[0])); }

// estimators/azimuth_fit.py direction_azimuth_and_sigma: azimuth of u_SF now and its 1-sigma.
//   u_NF = C_NF<-AF C_AF<-ISF C u;  g = d az / d u_NF = [-E, N, 0] / (N^2 + E^2)
//   L = g C_NF<-ISF [u_ISF]x;  v = [1, -L G, -(g C_NF<-AF x u_AF)[:2] (+ g C_NF<-SF du_dbeta)]
//   var = v^T P v + |L|^2 arw_var
inline void direction_azimuth_and_sigma(const V3& u_sf, const AzimuthOutputCfg& c, const M3& C, const double* G,
                                        double arw_var, bool use_du, double& az, double& sigma) {
    const V3 u_isf = mv<3, 3>(C, u_sf);
    const V3 u_af = mv<3, 3>(c.C_af_isf, u_isf);
    const V3 u_nf = mv<3, 3>(c.C_nf_af, u_af);
    const double h2 = std::max(u_nf[0] * u_nf[0] + u_nf[1] * u_nf[1], 1e-300);
    const V3 g = {-u_nf[1] / h2, u_nf[0] / h2, 0.0 / h2};
    const V3 gC = vm3(g, c.C_nf_af);
    const V3 L = cross3(vm3(gC, c.C_af_isf), u_isf);
    const int n = c.nP;
    std::vector<double> v(static_cast<size_t>(n), 0.0);
    v[0] = 1.0;
    for (int j = 0; j < 12; ++j) v[1 + j] = -(L[0] * G[j] + L[1] * G[12 + j] + L[2] * G[24 + j]);
    const V3 gu = cross3(gC, u_af);
    v[13] = -gu[0];
    v[14] = -gu[1];
    if (use_du) {
        const V3 r = vm3(vm3(gC, c.C_af_isf), C);
        for (int j = 0; j < 2; ++j) v[13 + j] = v[13 + j] + (r[0] * c.du[j] + r[1] * c.du[2 + j] + r[2] * c.du[4 + j]);
    }
    double var = 0.0;
    for (int j = 0; j < n; ++j) {
        double s = 0.0;
        for (int i = 0; i < n; ++i) s = s + v[i] * c.P[static_cast<size_t>(i) * n + j];
        var = var + s * v[j];
    }
    var = var + (L[0] * L[0] + L[1] * L[1] + L[2] * L[2]) * arw_var;
    az = azimuth_of_ned(u_nf);
    sigma = std::sqrt(std::max(var, 0.0));
}

// The numbers of A's output at time t for the propagated G (3 x 12) and C = C_ISF<-SF (row-major).
inline AzimuthOutputNumbers azimuth_output_numbers(const AzimuthOutputCfg& c, const double* G, const double* Cin,
                                                   double t) {
    AzimuthOutputNumbers o;
    M3 C;
    for (int k = 0; k < 9; ++k) C[k] = Cin[k];
    M3 C_nf_sf;
    if (c.has_solution) {
        V3 a{};
        for (int r = 0; r < 3; ++r) {
            double s = 0.0;
            for (int j = 0; j < 12; ++j) s = s + G[12 * r + j] * c.c_gyro[j];
            a[r] = s;
        }
        M3 I_a = eye<3>();
        const M3 S = skew(a);
        for (int k = 0; k < 9; ++k) I_a[k] = I_a[k] - S[k];
        C = mm<3, 3, 3>(I_a, C);
        C_nf_sf = mm<3, 3, 3>(mm<3, 3, 3>(c.C_nf_af, c.C_af_isf), C);
    } else {
        C_nf_sf = mm<3, 3, 3>(tr<3, 3>(c.C_isf_af), C);
    }
    const M3 C_nf_body = mm<3, 3, 3>(C_nf_sf, c.C_sf_body);
    const V3 e = euler_from_dcm(C_nf_body);
    o.roll = e[0];
    o.pitch = e[1];
    o.q = quat_from_dcm(C_nf_body);
    if (!c.has_solution || c.nP != 15) return o;
    const double arw_var = c.arw2 * std::max(t - c.launch_time_s, 0.0);
    const V3 x_body = {c.C_sf_body[0], c.C_sf_body[3], c.C_sf_body[6]};
    double hd, hs;
    direction_azimuth_and_sigma(x_body, c, C, G, arw_var, false, hd, hs);
    const double gap = std::isfinite(c.last_sample_s) ? t - c.last_sample_s : 0.0;
    const double rb = c.sigma_b * std::max(gap, 0.0);
    const double run_var = rb * rb;
    hs = std::sqrt(hs * hs + c.fm2 + run_var);
    o.heading = hd;
    o.heading_sigma = hs;
    if (!c.has_u) return o;
    if (c.aligned) {
        o.azimuth = hd;
        o.azimuth_sigma = hs;
    } else {
        V3 u = c.u_sf;
        if (c.has_du)
            for (int r = 0; r < 3; ++r) u[r] = u[r] - (c.du[2 * r] * c.c_tilt[0] + c.du[2 * r + 1] * c.c_tilt[1]);
        double az, as;
        direction_azimuth_and_sigma(u, c, C, G, arw_var, c.has_du, az, as);
        o.azimuth = az;
        o.azimuth_sigma = std::sqrt(as * as + c.fm2 + run_var);
    }
    o.launch_azimuth = azimuth_of_ned(mv<3, 3>(mm<3, 3, 3>(c.C_nf_af, c.C_af_isf), c.u_sf));
    return o;
}

}  // namespace azimuthd
