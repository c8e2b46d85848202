// Method D's deviation RLS (METHODS.md D; estimators/mag_deviation.py, which stays the reference):
// per body axis i, dT_i = h(psi, phi, theta)^T c_i with h = [1, sin psi, cos psi, phi, phi^2, theta,
// theta^2] (and, extended, [phi sin psi, phi cos psi, theta sin psi, theta cos psi]); the three axes
// share one gain matrix P. One observation:
//     k = P h / (lambda + h^T P h);  c_i += k (dT_i - h^T c_i);  P = sym((P - k (P h)^T) / lambda)
// plus the coverage bins and the a-priori residual sums, the modelled deviation, the corrected
// field, the residual sigma and the coverage figure, as the Pipeline calls them. The reference's
// operand order, no FMA contraction (CMakeLists.txt).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace azimuthd {

struct DeviationParamsC {
    double forgetting_factor = 1.0;
    double roll_limit_rad = 0.0, pitch_limit_rad = 0.0;
    int heading_bins = 12, roll_bins = 6, pitch_bins = 4, min_samples_per_bin = 5;
};

enum class DeviationCode { updated = 0, non_finite = 1, outside_limits = 2 };

struct Deviation {
    int n_per = 7;                        // 7 (seed) or 11 (extended)
    std::vector<double> coeffs;           // n_per x 3, row-major
    std::vector<double> P;                // n_per x n_per
    std::int64_t n = 0, n_resid = 0;
    double resid_sq_sum[3] = {0.0, 0.0, 0.0};
    std::vector<std::int64_t> heading_counts, roll_counts, pitch_counts;

    void regressor(double psi, double phi, double theta, double* h) const {
        const double s = std::sin(psi), c = std::cos(psi);
        h[0] = 1.0; h[1] = s; h[2] = c; h[3] = phi; h[4] = phi * phi; h[5] = theta; h[6] = theta * theta;
        if (n_per == 11) { h[7] = phi * s; h[8] = phi * c; h[9] = theta * s; h[10] = theta * c; }
    }

    // h^T coeffs (3)
    void model(double psi, double phi, double theta, double out[3]) const {
        double h[11];
        regressor(psi, phi, theta, h);
        for (int i = 0; i < 3; ++i) {
            double acc = 0.0;
            for (int j = 0; j < n_per; ++j) acc += h[j] * coeffs[3 * j + i];
            out[i] = acc;
        }
    }

    // T_ref = C_body_from_nav F (estimators/mag_deviation.py reference_field_body): (Rz Ry Rx)^T F
    static void reference_field_body(const double F[3], double psi, double phi, double theta, double out[3]) {
        const double cz = std::cos(psi), sz = std::sin(psi), cy = std::cos(theta), sy = std::sin(theta),
                     cx = std::cos(phi), sx = std::sin(phi);
        const double Rz[9] = {cz, -sz, 0.0, sz, cz, 0.0, 0.0, 0.0, 1.0};
        const double Ry[9] = {cy, 0.0, sy, 0.0, 1.0, 0.0, -sy, 0.0, cy};
        const double Rx[9] = {1.0, 0.0, 0.0, 0.0, cx, -sx, 0.0, sx, cx};
        double T[9], C[9];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) T[3 * i + j] = Rz[3 * i] * Ry[j] + Rz[3 * i + 1] * Ry[3 + j] + Rz[3 * i + 2] * Ry[6 + j];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) C[3 * i + j] = T[3 * i] * Rx[j] + T[3 * i + 1] * Rx[3 + j] + T[3 * i + 2] * Rx[6 + j];
        for (int i = 0; i < 3; ++i) out[i] = C[i] * F[0] + C[3 + i] * F[1] + C[6 + i] * F[2];
    }

    static int bin(double v, double lo, double hi, int nb) {  // -1: outside
        if (!(lo <= v && v <= hi)) return -1;
        return std::min(nb - 1, static_cast<int>((v - lo) / (hi - lo) * nb));
    }

    DeviationCode step(const double m[3], const double F[3], double psi, double phi, double theta,
                       const DeviationParamsC& p, double e_out[3]) {
        bool fin = std::isfinite(psi) && std::isfinite(phi) && std::isfinite(theta);
        for (int i = 0; i < 3; ++i) fin = fin && std::isfinite(m[i]) && std::isfinite(F[i]);
        if (!fin) return DeviationCode::non_finite;
        if (std::fabs(phi) > p.roll_limit_rad || std::fabs(theta) > p.pitch_limit_rad)
            return DeviationCode::outside_limits;
        const int n_h = n_per;
        double h[11], ref[3], dT[3], Ph[11], k[11];
        regressor(psi, phi, theta, h);
        reference_field_body(F, psi, phi, theta, ref);
        for (int i = 0; i < 3; ++i) dT[i] = m[i] - ref[i];
        const double lam = p.forgetting_factor;
        for (int i = 0; i < n_h; ++i) {
            double acc = 0.0;
            for (int j = 0; j < n_h; ++j) acc += P[n_h * i + j] * h[j];
            Ph[i] = acc;
        }
        double hPh = 0.0;
        for (int i = 0; i < n_h; ++i) hPh += h[i] * Ph[i];
        const double s = lam + hPh;
        for (int i = 0; i < n_h; ++i) k[i] = Ph[i] / s;
        double e[3];
        model(psi, phi, theta, e);
        for (int i = 0; i < 3; ++i) e[i] = dT[i] - e[i];
        for (int j = 0; j < n_h; ++j)
            for (int i = 0; i < 3; ++i) coeffs[3 * j + i] = coeffs[3 * j + i] + k[j] * e[i];
        std::vector<double> Pn(P.size());
        for (int i = 0; i < n_h; ++i)
            for (int j = 0; j < n_h; ++j) Pn[n_h * i + j] = (P[n_h * i + j] - k[i] * Ph[j]) / lam;
        for (int i = 0; i < n_h; ++i)
            for (int j = 0; j < n_h; ++j) P[n_h * i + j] = 0.5 * (Pn[n_h * i + j] + Pn[n_h * j + i]);
        // coverage bins (wrap_2pi of the heading)
        const double two_pi = 6.283185307179586;
        double hw = std::fmod(psi, two_pi);
        if (hw < 0.0) hw += two_pi;
        if (hw >= two_pi) hw = 0.0;
        heading_counts[std::min(p.heading_bins - 1, static_cast<int>(hw / two_pi * p.heading_bins))] += 1;
        int b = bin(phi, -p.roll_limit_rad, p.roll_limit_rad, p.roll_bins);
        if (b >= 0) roll_counts[b] += 1;
        b = bin(theta, -p.pitch_limit_rad, p.pitch_limit_rad, p.pitch_bins);
        if (b >= 0) pitch_counts[b] += 1;
        const bool burn = n < 3 * n_h;
        for (int i = 0; i < 3; ++i) resid_sq_sum[i] = resid_sq_sum[i] + (burn ? 0.0 : e[i] * e[i] / s);
        n_resid += burn ? 0 : 1;
        n += 1;
        for (int i = 0; i < 3; ++i) e_out[i] = e[i];
        return DeviationCode::updated;
    }

    void residual_sigma(double out[3]) const {
        const double d = static_cast<double>(std::max<std::int64_t>(1, n_resid));
        for (int i = 0; i < 3; ++i) out[i] = std::sqrt(resid_sq_sum[i] / d);
    }

    static double fraction(const std::vector<std::int64_t>& counts, int k) {
        int hit = 0;
        for (auto c : counts) hit += c >= k ? 1 : 0;
        return static_cast<double>(hit) / static_cast<double>(counts.size());
    }
};

}  // namespace azimuthd
