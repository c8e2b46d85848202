// The IMU input checks at the Pipeline's edge: the compiled twin of service/input_checks.py
// ImuInputChecks.check, which stays the reference and documents every check (non-finite, time
// backwards / restarted, out of range, saturated, frozen, gap). tests/test_core_input_checks.py
// proves them equal on recorded flights and on a faulted stream.
//
// Only the per-sample decisions live here. What a decision says (the event text, the counts per
// kind, the once-per-report-interval rate limit) stays in Python: it runs only on a bad sample,
// from the figures step() leaves in InputChecks::detail.
#pragma once

#include <cmath>

namespace azimuthd {

// step()'s verdict: the rejected kind (0 = use the sample) ...
enum InputCode : int { IC_OK = 0, IC_NON_FINITE = 1, IC_TIME_BACKWARDS = 2, IC_OUT_OF_RANGE = 3,
                       IC_SATURATED = 4, IC_FROZEN = 5 };
// ... or'ed with what else happened on this sample (each an event in the reference)
enum InputFlag : int { IF_TIME_RESET = 1 << 4, IF_RESET_END = 1 << 5, IF_GAP = 1 << 6, IF_FROZEN_END = 1 << 7 };

struct InputCheckLimits {
    double gyro_max_rad_s, accel_max_m_s2, clip_gyro_rad_s, clip_accel_m_s2;
    double int16_gyro_rad_s, int16_accel_m_s2;   // RAW_GYRO_LIMIT_RAD_S - 1e-9, RAW_ACCEL_LIMIT_M_S2 - 1e-6
    double frozen_s, gap_s, reset_jump_s, frozen_live_fraction, live_alpha;
    int clip_repeats, frozen_min_samples, reset_after_samples;
};

// The figures behind the last step's verdict and events (read only when step() != IC_OK).
struct InputDetail {
    double last_t_s = 0.0;        // the last used sample's time before this one
    double max_gyro_rad_s = 0.0, max_accel_m_s2 = 0.0;   // out_of_range
    bool at_int16 = false;        // saturated: at the int16 limit (else the clip run)
    int clip_n = 0;
    int behind_n = 0;             // time_reset
    int same_n = 0;               // frozen: identical samples so far
    double same_s = 0.0;          // frozen: over this long
    int frozen_end_n = 0;         // frozen_end: the identical samples of the run that ended
};

struct InputChecks {
    InputCheckLimits lim{};
    bool has_last_t = false;
    double last_t = 0.0;
    int behind_n = 0;
    bool has_behind_last_t = false;
    double behind_last_t = 0.0;
    bool restarted = false;
    bool has_prev = false;
    double prev[6] = {0, 0, 0, 0, 0, 0};
    int same_n = 0;
    double same_since_t = 0.0;
    bool frozen = false;
    double live = 0.0, live_at_run = 0.0;
    bool has_clip_prev = false;
    double clip_prev[6] = {0, 0, 0, 0, 0, 0};
    int clip_n = 0;
    int clip_run[6] = {0, 0, 0, 0, 0, 0};
    InputDetail detail{};

    // One sample (v = gyro rad/s then accel m/s^2, FC time t); int16_source: RAW_IMU / SCALED_IMU.
    int step(const double v[6], double t, bool int16_source) {
        int flags = 0;
        detail.last_t_s = last_t;
        bool finite = std::isfinite(t);
        for (int i = 0; i < 6; ++i) finite = finite && std::isfinite(v[i]);
        if (!finite) return IC_NON_FINITE;
        if (has_last_t && t <= last_t) {
            const double behind = last_t - t;
            if (behind > lim.reset_jump_s && (!has_behind_last_t || t > behind_last_t)) {
                behind_n += 1;
                has_behind_last_t = true;
                behind_last_t = t;
            } else {
                behind_n = 0;
                has_behind_last_t = false;
            }
            if (behind_n == lim.reset_after_samples) {
                restarted = true;
                detail.behind_n = behind_n;
                flags |= IF_TIME_RESET;
            }
            return IC_TIME_BACKWARDS | flags;
        }
        behind_n = 0;
        has_behind_last_t = false;
        if (restarted) {  // the restarted clock passed the old one
            restarted = false;
            last_t = t;
            has_last_t = true;
            return values(v, t, int16_source, IF_RESET_END);
        }
        if (has_last_t && t - last_t > lim.gap_s) flags |= IF_GAP;
        last_t = t;
        has_last_t = true;
        return values(v, t, int16_source, flags);
    }

  private:
    int values(const double v[6], double t, bool int16_source, int flags) {
        double a[6];
        for (int i = 0; i < 6; ++i) a[i] = std::fabs(v[i]);
        bool out = false;
        for (int i = 0; i < 3; ++i) out = out || a[i] > lim.gyro_max_rad_s || a[3 + i] > lim.accel_max_m_s2;
        if (out) {
            detail.max_gyro_rad_s = std::fmax(std::fmax(a[0], a[1]), a[2]);
            detail.max_accel_m_s2 = std::fmax(std::fmax(a[3], a[4]), a[5]);
            return IC_OUT_OF_RANGE | flags;
        }
        // per-axis runs of a bit-identical value above the clip threshold
        int mx = 0;
        for (int i = 0; i < 6; ++i) {
            const bool big = a[i] >= (i < 3 ? lim.clip_gyro_rad_s : lim.clip_accel_m_s2);
            const bool same = big && has_clip_prev && v[i] == clip_prev[i];
            clip_run[i] = same ? clip_run[i] + 1 : (big ? 1 : 0);
            if (clip_run[i] > mx) mx = clip_run[i];
            clip_prev[i] = v[i];
        }
        has_clip_prev = true;
        clip_n = mx;
        bool at16 = false;
        if (int16_source)
            for (int i = 0; i < 3; ++i) at16 = at16 || a[i] >= lim.int16_gyro_rad_s || a[3 + i] >= lim.int16_accel_m_s2;
        if (at16 || clip_n >= lim.clip_repeats) {
            detail.at_int16 = at16;
            detail.clip_n = clip_n;
            return IC_SATURATED | flags;
        }
        bool key_same = has_prev;
        for (int i = 0; i < 6 && key_same; ++i) key_same = v[i] == prev[i];
        if (key_same) {
            same_n += 1;
        } else {
            if (frozen) {
                frozen = false;
                detail.frozen_end_n = same_n;
                flags |= IF_FROZEN_END;
            }
            if (has_prev) {  // (same_n - 1) unchanged samples, then this changed one (EWMA)
                live = std::pow(1.0 - lim.live_alpha, static_cast<double>(same_n)) * live + lim.live_alpha;
                live_at_run = live;
            }
            for (int i = 0; i < 6; ++i) prev[i] = v[i];
            has_prev = true;
            same_n = 1;
            same_since_t = t;
        }
        if (same_n >= lim.frozen_min_samples && t - same_since_t >= lim.frozen_s &&
            live_at_run >= lim.frozen_live_fraction) {
            frozen = true;
            detail.same_n = same_n;
            detail.same_s = t - same_since_t;
            return IC_FROZEN | flags;
        }
        return IC_OK | flags;
    }
};

}  // namespace azimuthd
