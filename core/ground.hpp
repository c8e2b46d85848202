// The Pipeline's per-sample ground (pre-launch) state: what service/pipeline.py _step_azimuth does to
// each IMU sample before the take-off, in C++ (issue 19). Its Python reference stays and is what
// AZIMUTHD_CORE=python runs: estimators/azimuth.py azimuth_prelaunch_step (method A's delay line, whose
// oldest samples feed A's levelling accumulator) and estimators/declination.py rest_accumulate (method
// E's rest data: the still block that is filling and the last one that passed).
//
// GroundState holds A's delay line and levelling accumulator while A's AzimuthState lets the core hold
// them (service/hot_path.py: taken in from the AzimuthState at the first ground step, given back when
// Python reads Pipeline.azimuth), and E's two rest accumulators for the whole run (the Pipeline's
// ``rest`` and ``_rest_candidate`` are properties over them). The reference's operation order; the
// build has no FMA contraction (CMakeLists.txt). tests/test_core_ground.py proves them equal.
#pragma once

#include <array>
#include <cmath>
#include <deque>

#include "levelling.hpp"

namespace azimuthd {

// estimators/declination.py RestState: Welford means and sums of squared deviations at rest
struct RestAcc {
    long long n = 0;
    double gyro_mean[3] = {0, 0, 0}, gyro_m2[3] = {0, 0, 0};
    double accel_mean[3] = {0, 0, 0}, accel_m2[3] = {0, 0, 0};
    double mag_mean[3] = {0, 0, 0}, mag_m2[3] = {0, 0, 0};
};

// rest_accumulate: one sample (a non-finite one is skipped: false). Per component, with n' = n + 1:
// d = x - mean; mean' = mean + d / n'; m2' = m2 + d (x - mean') (core/levelling.hpp welford3).
inline bool rest_accumulate(RestAcc& s, const double g[3], const double a[3], const double m[3]) {
    for (int i = 0; i < 3; ++i)
        if (!(std::isfinite(g[i]) && std::isfinite(a[i]) && std::isfinite(m[i]))) return false;
    s.n += 1;
    const double n = static_cast<double>(s.n);
    welford3(g, s.gyro_mean, s.gyro_m2, n);
    welford3(a, s.accel_mean, s.accel_m2, n);
    welford3(m, s.mag_mean, s.mag_m2, n);
    return true;
}

struct GroundState {
    // method A's pre-launch part (AzimuthState.pending / .levelling) while the core holds it
    bool a_held = false;
    double buffer_s = 0.0;                         // AzimuthParams.prelaunch_buffer_s
    std::deque<std::array<double, 7>> pending;     // the delay line: (time, gyro (3), accel (3)), oldest first
    LevellingAcc a_levelling;                      // untimed: the samples out of the delay line
    // method E: the Pipeline's rest (the last passing still block's data) and the block filling
    RestAcc rest, candidate;
};

// azimuth_prelaunch_step: the sample into the delay line; the samples older than buffer_s before it
// out of it into A's levelling (untimed). A non-finite sample is dropped, as the reference drops it.
inline void prelaunch_step(GroundState& s, const double g[3], const double a[3], double t) {
    for (int i = 0; i < 3; ++i)
        if (!(std::isfinite(g[i]) && std::isfinite(a[i]))) return;
    s.pending.push_back({t, g[0], g[1], g[2], a[0], a[1], a[2]});
    const double cut = t - s.buffer_s;
    while (!s.pending.empty() && s.pending.front()[0] < cut) {
        const std::array<double, 7>& e = s.pending.front();
        levelling_step(s.a_levelling, e.data() + 1, e.data() + 4, NAN, 0.25);  // untimed: batch_s unused
        s.pending.pop_front();
    }
}

// _step_azimuth's pre-launch branch for one sample (the phase already stepped on it): A's delay line,
// the rest data (m: the magnetometer, nullptr when the sample has none), and at the end of a still
// block (block_ended: the phases' block_start_s is this sample's time) the rest the block leaves:
// the data so far when the block passed on this sample, else none.
inline void ground_step(GroundState& s, const double g[3], const double a[3], const double* m, double t,
                        bool block_ended, bool block_passed) {
    prelaunch_step(s, g, a, t);
    if (m != nullptr) rest_accumulate(s.candidate, g, a, m);
    if (block_ended) {
        if (block_passed) {
            s.rest = s.candidate;
        } else {
            s.candidate = RestAcc();
            s.rest = RestAcc();
        }
    }
}

}  // namespace azimuthd
