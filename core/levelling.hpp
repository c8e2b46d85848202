// The rest accumulator: running means and spreads of the rate and the specific force at rest,
// with the batch means behind the batch-means standard error (the compiled twin of
// estimators/levelling.py levelling_step, which stays the reference and holds the derivation;
// tests/test_core_levelling.py proves them equal).
//
// Welford per component: d = x - mean; mean' = mean + d / n; m2' = m2 + d (x - mean').
// Timed samples are cut into batches of batch_s seconds; each closed batch's mean feeds a second
// Welford sum over the batches. Operand order is the reference's (no FMA contraction: CMakeLists.txt).
#pragma once

#include <cmath>

namespace azimuthd {

struct LevellingAcc {
    double n = 0.0;                    // samples (an integer count, exact in a double)
    double accel_mean_m_s2[3] = {0, 0, 0};
    double accel_m2[3] = {0, 0, 0};
    double gyro_mean_rad_s[3] = {0, 0, 0};
    double gyro_m2[3] = {0, 0, 0};
    bool timed = false;                // t_first_s / t_last_s hold the first and last timed sample
    double t_first_s = NAN, t_last_s = NAN;
    bool batch_open = false;           // the open batch: start time, count, sums
    double batch_t0_s = 0.0, batch_k = 0.0;
    double batch_accel_sum[3] = {0, 0, 0}, batch_gyro_sum[3] = {0, 0, 0};
    double nb = 0.0;                   // closed batches
    bool has_stats = false;            // Welford over the closed batches' means
    double batch_accel_mean[3] = {0, 0, 0}, batch_accel_m2[3] = {0, 0, 0};
    double batch_gyro_mean[3] = {0, 0, 0}, batch_gyro_m2[3] = {0, 0, 0};
};

inline void welford3(const double x[3], double mean[3], double m2[3], double n) {
    for (int i = 0; i < 3; ++i) {
        const double d = x[i] - mean[i];
        const double mn = mean[i] + d / n;
        m2[i] = m2[i] + d * (x[i] - mn);
        mean[i] = mn;
    }
}

// One sample; time_s non-finite = untimed. A non-finite rate or force is skipped (false).
inline bool levelling_step(LevellingAcc& s, const double g[3], const double a[3], double time_s, double batch_s) {
    for (int i = 0; i < 3; ++i)
        if (!(std::isfinite(g[i]) && std::isfinite(a[i]))) return false;
    s.n += 1.0;
    welford3(a, s.accel_mean_m_s2, s.accel_m2, s.n);
    welford3(g, s.gyro_mean_rad_s, s.gyro_m2, s.n);
    if (!std::isfinite(time_s)) return true;
    if (s.batch_open && time_s - s.batch_t0_s >= batch_s) {  // close the open batch, start one here
        const double k = s.batch_k;
        s.nb += 1.0;
        double bam[3], bgm[3];
        for (int i = 0; i < 3; ++i) { bam[i] = s.batch_accel_sum[i] / k; bgm[i] = s.batch_gyro_sum[i] / k; }
        if (s.has_stats) {
            welford3(bam, s.batch_accel_mean, s.batch_accel_m2, s.nb);
            welford3(bgm, s.batch_gyro_mean, s.batch_gyro_m2, s.nb);
        } else {
            for (int i = 0; i < 3; ++i) {
                s.batch_accel_mean[i] = bam[i]; s.batch_accel_m2[i] = 0.0;
                s.batch_gyro_mean[i] = bgm[i]; s.batch_gyro_m2[i] = 0.0;
            }
            s.has_stats = true;
        }
        s.batch_open = false;
    }
    if (!s.batch_open) {
        s.batch_open = true;
        s.batch_t0_s = time_s;
        s.batch_k = 1.0;
        for (int i = 0; i < 3; ++i) { s.batch_accel_sum[i] = a[i]; s.batch_gyro_sum[i] = g[i]; }
    } else {
        s.batch_k += 1.0;
        for (int i = 0; i < 3; ++i) {
            s.batch_accel_sum[i] = s.batch_accel_sum[i] + a[i];
            s.batch_gyro_sum[i] = s.batch_gyro_sum[i] + g[i];
        }
    }
    if (!s.timed) { s.timed = true; s.t_first_s = time_s; }
    s.t_last_s = time_s;
    return true;
}

// The accumulator as a flat float64 vector (what estimators/core.py packs from and unpacks into
// estimators.levelling.LevellingState; core/bindings.cpp LEVELLING_FIELDS names the order): one
// layout for every binding that hands an accumulator across.
constexpr int LEVELLING_PACKED_SIZE = 38;

inline void levelling_pack(const LevellingAcc& s, double* o) {
    int j = 0;
    o[j++] = s.n;
    for (double v : s.accel_mean_m_s2) o[j++] = v;
    for (double v : s.accel_m2) o[j++] = v;
    for (double v : s.gyro_mean_rad_s) o[j++] = v;
    for (double v : s.gyro_m2) o[j++] = v;
    o[j++] = s.timed ? s.t_first_s : NAN;
    o[j++] = s.timed ? s.t_last_s : NAN;
    o[j++] = s.batch_open ? 1.0 : 0.0;
    o[j++] = s.batch_t0_s;
    o[j++] = s.batch_k;
    for (double v : s.batch_accel_sum) o[j++] = v;
    for (double v : s.batch_gyro_sum) o[j++] = v;
    o[j++] = s.nb;
    o[j++] = s.has_stats ? 1.0 : 0.0;
    for (double v : s.batch_accel_mean) o[j++] = v;
    for (double v : s.batch_accel_m2) o[j++] = v;
    for (double v : s.batch_gyro_mean) o[j++] = v;
    for (double v : s.batch_gyro_m2) o[j++] = v;
}

inline LevellingAcc levelling_unpack(const double* p) {
    LevellingAcc s;
    int j = 0;
    s.n = p[j++];
    for (double& v : s.accel_mean_m_s2) v = p[j++];
    for (double& v : s.accel_m2) v = p[j++];
    for (double& v : s.gyro_mean_rad_s) v = p[j++];
    for (double& v : s.gyro_m2) v = p[j++];
    s.t_first_s = p[j++];
    s.t_last_s = p[j++];
    s.timed = std::isfinite(s.t_first_s);
    s.batch_open = p[j++] != 0.0;
    s.batch_t0_s = p[j++];
    s.batch_k = p[j++];
    for (double& v : s.batch_accel_sum) v = p[j++];
    for (double& v : s.batch_gyro_sum) v = p[j++];
    s.nb = p[j++];
    s.has_stats = p[j++] != 0.0;
    for (double& v : s.batch_accel_mean) v = p[j++];
    for (double& v : s.batch_accel_m2) v = p[j++];
    for (double& v : s.batch_gyro_mean) v = p[j++];
    for (double& v : s.batch_gyro_m2) v = p[j++];
    return s;
}

}  // namespace azimuthd
