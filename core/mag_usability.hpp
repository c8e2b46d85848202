// Magnetometer usability: the compiled twin of estimators/mag_usability.py (mag_usability_step,
// mag_usability_stale), which stays the reference and holds the reasoning behind every test (field
// norm, dip, frozen, stuck axis, too slow). tests/test_core_mag_usability.py proves them equal.
//
// The state is the reference's MagUsabilityState field for field (tuples as vectors; a None time
// as a has_ flag; usable None/False/True as -1/0/1); the reason is formatted here with the
// reference's figures and precision (printf's %.Nf rounds as Python's format does).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

namespace azimuthd {

struct MagUsabilityParams {
    double field_norm_gauss = 0.5, field_dip_rad = 0.0, norm_tolerance_fraction = 0.25, dip_tolerance_rad = 0.0;
    double window_s = 2.0, frozen_s = 3.0, min_rate_hz = 1.0, rate_window_s = 5.0;
    bool has_full_scale = false;
    double full_scale_gauss = 0.0, min_expected_change_gauss = 0.03, motion_step_rad = 0.0,
           motion_rate_floor_rad_s = 0.0;
};

struct MagWindowEntry {
    double t, ratio, dip;
};

struct MagVerdictOut {
    bool usable = false;
    std::string reason;
    bool new_sample = false, changed = false;
    double norm_ratio = NAN, dip_rad = NAN, rate_hz = NAN;
};

inline std::string fmt(const char* f, double a) {
    char b[160];
    std::snprintf(b, sizeof b, f, a);
    return b;
}

inline double rad2deg(double x) { return x * (180.0 / M_PI); }   // CPython's math.degrees

struct MagUsability {
    bool has_last_mag = false;
    double last_mag[3] = {0, 0, 0};
    bool has_changed_s = false;
    double changed_s = 0.0;
    bool has_axis_changed[3] = {false, false, false};
    double axis_changed_s[3] = {0, 0, 0};
    std::vector<double> new_times;
    std::vector<MagWindowEntry> window;
    bool has_first_s = false;
    double first_s = 0.0;
    bool has_last_call_s = false;
    double last_call_s = 0.0;
    double expected_change_gauss = 0.0;
    double axis_expected_change_gauss[3] = {0, 0, 0};
    double turned_rad = 0.0;
    std::vector<double> motion_marks;
    int usable = -1;   // None
    std::string reason = "no magnetometer sample yet";

    // _motion: the change the gyros predict since the previous call (dm = -(w x m) dt), the turn
    // angle and its motion marks; an interval longer than rate_window_s adds nothing.
    void motion(double t, const double m[3], bool gyro_ok, const double w[3], const MagUsabilityParams& p,
                double& exp_all, double exp_axis[3], double& turned, std::vector<double>& marks) const {
        exp_all = expected_change_gauss;
        for (int i = 0; i < 3; ++i) exp_axis[i] = axis_expected_change_gauss[i];
        turned = turned_rad;
        marks = motion_marks;
        if (!gyro_ok || !has_last_call_s) return;
        const double dt = t - last_call_s;
        const double wn = std::sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
        if (std::isfinite(wn) && 0.0 < dt && dt <= p.rate_window_s && wn >= p.motion_rate_floor_rad_s) {
            const double dm[3] = {std::fabs(m[1] * w[2] - m[2] * w[1]) * dt, std::fabs(m[2] * w[0] - m[0] * w[2]) * dt,
                                  std::fabs(m[0] * w[1] - m[1] * w[0]) * dt};
            exp_all += std::sqrt(dm[0] * dm[0] + dm[1] * dm[1] + dm[2] * dm[2]);
            for (int i = 0; i < 3; ++i) exp_axis[i] = exp_axis[i] + dm[i];
            const double step = wn * dt;
            if (std::floor((turned + step) / p.motion_step_rad) > std::floor(turned / p.motion_step_rad)) {
                std::vector<double> kept;
                for (double x : marks)
                    if (t - x < p.rate_window_s) kept.push_back(x);
                kept.push_back(t);
                marks.swap(kept);
            }
            turned += step;
        }
    }

    static double median_finite(std::vector<double> v) {
        v.erase(std::remove_if(v.begin(), v.end(), [](double x) { return !std::isfinite(x); }), v.end());
        if (v.empty()) return NAN;
        std::sort(v.begin(), v.end());
        const size_t n = v.size();
        return n % 2 ? v[n / 2] : (v[n / 2 - 1] + v[n / 2]) / 2.0;   // numpy's median: the mean of the two
    }

    // mag_usability_step: m finite (the caller checked), tilt given when has_tilt (finite),
    // gyro: has_gyro = motion known, gyro_ok = 3 values; hard iron subtracted for norm and dip.
    MagVerdictOut step(double t, const double m[3], bool has_tilt, double roll, double pitch, bool has_gyro,
                       bool gyro_ok, const double w[3], bool has_hi, const double hi[3], const MagUsabilityParams& p) {
        const double first = has_first_s ? first_s : t;
        bool newer = !has_last_mag;
        for (int i = 0; i < 3 && !newer; ++i) newer = m[i] != last_mag[i];
        double exp_all, exp_axis[3], turned;
        std::vector<double> marks;
        motion(t, m, has_gyro && gyro_ok, w, p, exp_all, exp_axis, turned, marks);
        if (newer) exp_all = 0.0;
        if (has_last_mag)
            for (int i = 0; i < 3; ++i) exp_axis[i] = m[i] != last_mag[i] ? 0.0 : exp_axis[i];
        bool moving = false;
        if (has_gyro)
            for (double x : marks) moving = moving || t - x < p.rate_window_s;
        double axis_changed[3];
        for (int i = 0; i < 3; ++i)
            axis_changed[i] = (!has_last_mag || m[i] != last_mag[i] || !has_axis_changed[i]) ? t : axis_changed_s[i];
        const double ch_s = newer ? t : changed_s;
        std::vector<double> times;
        for (double x : new_times)
            if (t - x < p.rate_window_s) times.push_back(x);
        if (newer) times.push_back(t);
        std::vector<MagWindowEntry> win;
        for (const MagWindowEntry& e : window)
            if (t - e.t < p.window_s) win.push_back(e);
        if (newer) {
            double mc[3] = {m[0], m[1], m[2]};
            if (has_hi)
                for (int i = 0; i < 3; ++i) mc[i] = m[i] - hi[i];
            const double ratio = std::sqrt(mc[0] * mc[0] + mc[1] * mc[1] + mc[2] * mc[2]) / p.field_norm_gauss;
            double dip = NAN;
            if (has_tilt) {  // m_lev = R_y(pitch) R_x(roll) m
                const double cr = std::cos(roll), sr = std::sin(roll), cp = std::cos(pitch), sp = std::sin(pitch);
                const double my = cr * mc[1] - sr * mc[2];
                const double mz1 = sr * mc[1] + cr * mc[2];
                const double mx = cp * mc[0] + sp * mz1;
                const double mz = -sp * mc[0] + cp * mz1;
                dip = std::atan2(mz, std::hypot(mx, my));
            }
            win.push_back({t, ratio, dip});
        }
        std::vector<double> ratios, dips;
        for (const MagWindowEntry& e : win) {
            ratios.push_back(e.ratio);
            dips.push_back(e.dip);
        }
        MagVerdictOut v;
        v.new_sample = newer;
        v.norm_ratio = median_finite(ratios);
        v.dip_rad = median_finite(dips);
        const double span = std::min(p.rate_window_s, t - first);
        const double nt = static_cast<double>(times.size());
        v.rate_hz = span > 0 && times.size() > 1 ? (nt - 1) / span : NAN;

        std::string why;
        const double mmax = std::max(std::max(std::fabs(m[0]), std::fabs(m[1])), std::fabs(m[2]));
        if (p.has_full_scale && mmax >= p.full_scale_gauss) {
            char b[200];
            std::snprintf(b, sizeof b, "saturated: |axis| %.2f G >= full scale %.2f G", mmax, p.full_scale_gauss);
            why = b;
        } else if (has_gyro && t - ch_s >= p.frozen_s && exp_all >= p.min_expected_change_gauss) {
            char b[200];
            std::snprintf(b, sizeof b, "frozen: identical samples for %.1f s while the gyros predict a %.3f G change",
                          t - ch_s, exp_all);
            why = b;
        } else if (has_gyro) {
            for (int i = 0; i < 3; ++i) {
                if (t - axis_changed[i] >= p.frozen_s && exp_axis[i] >= p.min_expected_change_gauss &&
                    t - ch_s < p.frozen_s) {
                    char b[200];
                    std::snprintf(b, sizeof b, "saturated: axis %c stuck at %+.3f G for %.1f s while the others change",
                                  "xyz"[i], m[i], t - axis_changed[i]);
                    why = b;
                    break;
                }
            }
        }
        if (why.empty() && moving && t - first >= p.rate_window_s && !(nt / p.rate_window_s >= p.min_rate_hz)) {
            char b[200];
            std::snprintf(b, sizeof b, "too slow: %.2f new samples/s < %.1f Hz", nt / p.rate_window_s, p.min_rate_hz);
            why = b;
        }
        if (why.empty() && std::isfinite(v.norm_ratio) && std::fabs(v.norm_ratio - 1.0) > p.norm_tolerance_fraction) {
            char b[200];
            std::snprintf(b, sizeof b, "field norm %.3f G vs the model's %.3f G (off by %.0f %% > %.0f %%)",
                          v.norm_ratio * p.field_norm_gauss, p.field_norm_gauss, 100 * std::fabs(v.norm_ratio - 1),
                          100 * p.norm_tolerance_fraction);
            why = b;
        }
        if (why.empty() && std::isfinite(v.dip_rad) && std::fabs(v.dip_rad - p.field_dip_rad) > p.dip_tolerance_rad) {
            char b[200];
            std::snprintf(b, sizeof b, "dip %.1f deg vs the model's %.1f deg (off by more than %.0f deg)",
                          rad2deg(v.dip_rad), rad2deg(p.field_dip_rad), rad2deg(p.dip_tolerance_rad));
            why = b;
        }
        // the state after this sample (both branches below)
        for (int i = 0; i < 3; ++i) {
            last_mag[i] = m[i];
            has_axis_changed[i] = true;
            axis_changed_s[i] = axis_changed[i];
            axis_expected_change_gauss[i] = exp_axis[i];
        }
        has_last_mag = true;
        has_changed_s = true;
        changed_s = ch_s;
        new_times.swap(times);
        window.swap(win);
        has_first_s = true;
        first_s = first;
        has_last_call_s = true;
        last_call_s = t;
        expected_change_gauss = exp_all;
        turned_rad = turned;
        motion_marks.swap(marks);
        if (why.empty() && t - first < p.window_s) {  // not judged before a window of samples exists
            char b[200];
            std::snprintf(b, sizeof b, "being checked (%.1f of %.1f s of samples)", t - first, p.window_s);
            usable = -1;
            reason = b;
            v.usable = false;
            v.reason = reason;
            v.changed = false;
            return v;
        }
        const int now = why.empty() ? 1 : 0;
        v.usable = now == 1;
        v.changed = now != usable;
        v.reason = why;
        usable = now;
        reason = why;
        return v;
    }

    // mag_usability_stale: no sample at t. Returns false when there is no verdict (None).
    bool stale(double t, bool has_gyro, bool gyro_ok, const double w[3], const MagUsabilityParams& p, MagVerdictOut& v) {
        if (has_last_mag && has_gyro) {
            double exp_all, exp_axis[3], turned;
            std::vector<double> marks;
            motion(t, last_mag, gyro_ok, w, p, exp_all, exp_axis, turned, marks);
            has_last_call_s = true;
            last_call_s = t;
            expected_change_gauss = exp_all;
            for (int i = 0; i < 3; ++i) axis_expected_change_gauss[i] = exp_axis[i];
            turned_rad = turned;
            motion_marks.swap(marks);
        }
        if (!has_changed_s || t - changed_s < p.frozen_s || reason.rfind("no samples", 0) == 0) return false;
        v = MagVerdictOut{};
        v.reason = fmt("no samples for %.1f s", t - changed_s);
        v.changed = usable != 0;
        usable = 0;
        reason = v.reason;
        return true;
    }
};

}  // namespace azimuthd
