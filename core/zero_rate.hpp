// Rest detection and the zero-rate updates of method C's gyro biases (estimators/zero_rate.py, which
// stays the reference; VQF's rest bias estimation the anchor). The reference's operand order, no FMA
// contraction (CMakeLists.txt).
// - rest_step: per filter step, the rate and specific force within gyro/accel_deviation of their
//   first-order low-pass (a = 1 - exp(-dt / tau)), the low-passed rate within max_rate per axis, for
//   min_rest_s; then the mean rate of the run so far, later of each chunk_s chunk; its per-axis
//   variance s^2 / n (s^2 the run's scatter), floored at mean_sigma_floor^2.
// - attitude_update: z = b_g + C_BP (w_ie_P + w_eP_P), H = [[v x], I, 0, C_BP, C_BP, 0 ...], v = C_BP W;
// - heading_update (platform formulation): z = b + C_BH e_z w_v, H = [0, (C_HB)_row3^T, I],
//   R = diag(var) + W_earth^2 I, psi_H not updated (its gain row zeroed).
// Both gated at gate_chi2 on 3 dof, Joseph form, P symmetrised.
#pragma once

#include <cmath>

#include "polar_attitude.hpp"
#include "polar_heading.hpp"

namespace azimuthd {
namespace zero_rate {

using polar::dot3;

// estimators.zero_rate.ZeroRateParams
struct Params {
    double gyro_deviation_rad_s, accel_deviation_m_s2, max_rate_rad_s, lowpass_tau_s, min_rest_s, chunk_s,
        mean_sigma_floor_rad_s, gate_chi2;
};

// estimators.zero_rate.ZeroRateState: gyro_lp / accel_lp are set iff has_time; sum, run sums and
// chunk_start iff has_rest (the reference sets and clears them together)
struct State {
    bool has_time = false;
    double time_s = 0.0;
    V3 gyro_lp{}, accel_lp{};
    bool has_rest = false;
    double rest_since_s = 0.0;
    bool reported = false;
    long n = 0;
    V3 sum{};
    long run_n = 0;
    V3 run_sum{}, run_sum_sq{};
    double chunk_start_s = 0.0;
};

// estimators.zero_rate.RestRate
struct RestRate {
    V3 mean{}, var{};
    long n = 0;
    double rest_s = 0.0;
};

constexpr double EARTH_RATE_RAD_S = 7.292115e-5;  // estimators.polar_heading.EARTH_RATE_RAD_S

// rest_step: true with `out` filled when a measurement is due
inline bool rest_step(State& s, double t, const V3& w, const V3& f, const Params& p, RestRate& out) {
    if (!(std::isfinite(t) && finite3(w) && finite3(f))) return false;
    if (!s.has_time || t <= s.time_s) {
        s = State{};
        s.has_time = true;
        s.time_s = t;
        s.gyro_lp = w;
        s.accel_lp = f;
        return false;
    }
    const double a = 1.0 - std::exp(-(t - s.time_s) / p.lowpass_tau_s);
    V3 w_lp, f_lp, dw, df;
    for (int i = 0; i < 3; ++i) {
        w_lp[i] = s.gyro_lp[i] + a * (w[i] - s.gyro_lp[i]);
        f_lp[i] = s.accel_lp[i] + a * (f[i] - s.accel_lp[i]);
        dw[i] = w[i] - w_lp[i];
        df[i] = f[i] - f_lp[i];
    }
    const double max_lp = std::max(std::fabs(w_lp[0]), std::max(std::fabs(w_lp[1]), std::fabs(w_lp[2])));
    const bool still = dot3(dw, dw) <= p.gyro_deviation_rad_s * p.gyro_deviation_rad_s &&
                       dot3(df, df) <= p.accel_deviation_m_s2 * p.accel_deviation_m_s2 && max_lp <= p.max_rate_rad_s;
    const State prev = s;
    s = State{};
    s.has_time = true;
    s.time_s = t;
    s.gyro_lp = w_lp;
    s.accel_lp = f_lp;
    if (!still) return false;
    s.has_rest = true;
    if (!prev.has_rest) {
        s.rest_since_s = t;
        s.n = 1;
        s.sum = w;
        s.run_n = 1;
        s.run_sum = w;
        for (int i = 0; i < 3; ++i) s.run_sum_sq[i] = w[i] * w[i];
        s.chunk_start_s = t;
        return false;
    }
    s.rest_since_s = prev.rest_since_s;
    s.reported = prev.reported;
    s.n = prev.n + 1;
    s.run_n = prev.run_n + 1;
    for (int i = 0; i < 3; ++i) {
        s.sum[i] = prev.sum[i] + w[i];
        s.run_sum[i] = prev.run_sum[i] + w[i];
        s.run_sum_sq[i] = prev.run_sum_sq[i] + w[i] * w[i];
    }
    s.chunk_start_s = prev.chunk_start_s;
    const bool due = !s.reported ? (t - s.rest_since_s + 1e-9 >= p.min_rest_s)
                                 : (t - s.chunk_start_s + 1e-9 >= p.chunk_s);
    if (!due || s.n < 1 || s.run_n < 2) return false;
    const double rn = static_cast<double>(s.run_n), n = static_cast<double>(s.n);
    const double floor2 = p.mean_sigma_floor_rad_s * p.mean_sigma_floor_rad_s;
    for (int i = 0; i < 3; ++i) {
        const double run_mean = s.run_sum[i] / rn;
        const double s2 = std::max((s.run_sum_sq[i] - rn * run_mean * run_mean) / (rn - 1.0), 0.0);
        out.var[i] = std::max(s2 / n, floor2);
        out.mean[i] = s.sum[i] / n;
    }
    out.n = s.n;
    out.rest_s = t - s.rest_since_s;
    s.reported = true;
    s.n = 0;
    s.sum = {0.0, 0.0, 0.0};
    s.chunk_start_s = t;
    return true;
}

// _kalman: one gated linear update of an N-state P with a 3 x N H; false (dx untouched) when gated
// out. S = H P H^T + R, ratio = z^T S^-1 z / gate, K = (P H^T) S^-1 (rows `keep` zeroed),
// P = sym((I - K H) P (I - K H)^T + K R K^T), dx = K z.
template <int N>
inline bool kalman(Mat<N, N>& P, const Mat<3, N>& H, const V3& z, const M3& R, double gate, int keep, double& ratio,
                   std::array<double, N>& dx) {
    const Mat<N, 3> Ht = tr<3, N>(H);
    const Mat<3, 3> HPHt = mm<3, N, 3>(mm<3, N, N>(H, P), Ht);
    M3 S;
    for (int i = 0; i < 9; ++i) S[i] = HPHt[i] + R[i];
    const M3 S_inv = inv<3>(S);
    ratio = polar::quad3(z, S_inv) / gate;
    if (!(ratio <= 1.0)) return false;
    Mat<N, 3> K = mm<N, 3, 3>(mm<N, N, 3>(P, Ht), S_inv);
    if (keep >= 0)
        for (int m = 0; m < 3; ++m) K[keep * 3 + m] = 0.0;
    Mat<N, N> I_KH = mm<N, 3, N>(K, H);
    for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) I_KH[i * N + j] = (i == j ? 1.0 : 0.0) - I_KH[i * N + j];
    const Mat<N, N> A = mm<N, N, N>(mm<N, N, N>(I_KH, P), tr<N, N>(I_KH));
    const Mat<N, N> B = mm<N, 3, N>(mm<N, 3, 3>(K, R), tr<N, 3>(K));
    Mat<N, N> Pn;
    for (int i = 0; i < N * N; ++i) Pn[i] = A[i] + B[i];
    for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) P[i * N + j] = 0.5 * (Pn[i * N + j] + Pn[j * N + i]);
    dx = mv<N, 3>(K, z);
    return true;
}

enum Result : int { FUSED = 0, NOT_READY = 1, GATED_OUT = 2 };  // ZeroRateDiag: fused / the reasons

inline M3 diag3(const V3& v, double add) { return {v[0] + add, 0.0, 0.0, 0.0, v[1] + add, 0.0, 0.0, 0.0, v[2] + add}; }

// attitude_zero_rate_update on the attitude filter's state
inline int attitude_update(polar::State& st, const RestRate& r, const Params& p, double& ratio) {
    ratio = NAN;
    if (!st.initialised) return NOT_READY;
    const polar::XVec& xh = st.x_hat;
    const M3 C_BP = tr<3, 3>(dcm_from_quat(st.q_P_from_body));
    const V3 v = mv<3, 3>(C_BP, V3{xh[6] + xh[9], xh[7] + xh[10], xh[8] + xh[11]});
    V3 z;
    for (int i = 0; i < 3; ++i) z[i] = r.mean[i] - (xh[i] + v[i]);
    Mat<3, polar::NS> H{};
    const M3 sk = skew(v);
    for (int m = 0; m < 3; ++m) {
        for (int j = 0; j < 3; ++j) {
            H[m * polar::NS + j] = sk[m * 3 + j];
            H[m * polar::NS + 9 + j] = C_BP[m * 3 + j];
            H[m * polar::NS + 12 + j] = C_BP[m * 3 + j];
        }
        H[m * polar::NS + 3 + m] = 1.0;
    }
    polar::PMat P = st.P;
    std::array<double, polar::NS> dx;
    if (!kalman<polar::NS>(P, H, z, diag3(r.var, 0.0), p.gate_chi2, -1, ratio, dx)) return GATED_OUT;
    st.q_P_from_body = quat_unit(quat_mul(st.q_P_from_body, quat_from_rotvec({dx[0], dx[1], dx[2]})));
    for (int i = 0; i < polar::NX; ++i) st.x_hat[i] = xh[i] + dx[3 + i];
    st.P = P;
    return FUSED;
}

// heading_zero_rate_update on the heading filter's state (platform formulation only)
inline int heading_update(polar_heading::State& st, const RestRate& r, const Params& p, double& ratio) {
    ratio = NAN;
    if (!(st.initialised && st.platform && st.has_q)) return NOT_READY;
    constexpr int N = polar_heading::NM;  // the platform formulation's 5 states: [psi_H, w_v, b(3)]
    const M3 C = dcm_from_quat(st.q_P_from_body);
    const V3 up{C[6], C[7], C[8]};  // e_z^T C_HB: H's vertical in body axes
    V3 z;
    for (int i = 0; i < 3; ++i) z[i] = r.mean[i] - (st.x[2 + i] + up[i] * st.x[1]);
    Mat<3, N> H{};
    for (int m = 0; m < 3; ++m) {
        H[m * N + 1] = up[m];
        H[m * N + 2 + m] = 1.0;
    }
    Mat<N, N> P = st.P;
    std::array<double, N> dx;
    if (!kalman<N>(P, H, z, diag3(r.var, EARTH_RATE_RAD_S * EARTH_RATE_RAD_S), p.gate_chi2, 0, ratio, dx))
        return GATED_OUT;
    for (int i = 0; i < N; ++i) st.x[i] = st.x[i] + dx[i];
    st.x[0] = wrap_2pi(st.x[0]);
    st.P = P;
    return FUSED;
}

}  // namespace zero_rate
}  // namespace azimuthd
