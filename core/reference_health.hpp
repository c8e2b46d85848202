// Health of the trusted attitude reference, the FC's own estimate (the compiled twin of
// estimators/reference_health.py, which stays the reference and holds the derivation): signalled
// status, freshness, and agreement with our gyro-only attitude over anchors (C_fc P^T = I + [d x],
// P = C_fc(t_a) C_gyro(t_a)^T C_gyro(t); |d_xy|, |d_z| against n_sigma sqrt(2 sigma_fc^2 + drift^2)
// + margin); losing trust latches. Reasons are codes here, worded by estimators/core.py.
#pragma once

#include <memory>
#include <vector>

#include "ahrs_math.hpp"

namespace azimuthd {

constexpr double INTERVAL_AVERAGING = 0.2;

struct HealthParams {
    bool require_horiz_pos_ok;
    double max_attitude_age_s, anchor_period_s, window_s, sigma_fc_tilt_rad, sigma_fc_yaw_rad, sigma_bias_rad_s,
        check_period_s, n_sigma, margin_rad, retrust_hold_s, status_wait_s;
};

struct Anchor {
    double t_a;
    M3 C_fc, C_g;
    double v_a;
};
using Anchors = std::shared_ptr<const std::vector<Anchor>>;  // replaced, never edited in place

// reference_health._signals_bad and the reasons built on it
enum class Signal { none, system_status, no_status_yet, attitude_not_ok, horiz_pos_lost };

struct Health {
    bool has_system_status = false;
    long system_status = 0;
    int attitude_ok = -1;  // -1 None, 0 False, 1 True
    int horiz_pos_ok = -1;
    bool has_fc_time = false;
    double fc_time_s = 0.0;
    bool has_first_attitude = false;
    double first_attitude_s = 0.0;  // the first ATTITUDE checked: the status wait's start
    bool has_interval = false;
    double attitude_interval_s = 0.0;
    Anchors anchors = std::make_shared<const std::vector<Anchor>>();
    double max_discrepancy_rad = 0.0;
    bool has_check_time = false;
    double check_time_s = 0.0;
    bool diverged = false;
    bool has_good_since = false;
    double good_since_s = 0.0;
    bool ever_trusted = false, latched_out = false, silent_divergence = false;
    const char* reason = "no FC attitude yet";
};

// reference_health.health_status_missing: no estimator status within status_wait_s of the first ATTITUDE
inline bool status_missing(const Health& s, const HealthParams& p, double time_s) {
    return s.attitude_ok == -1 && s.has_first_attitude && time_s - s.first_attitude_s >= p.status_wait_s;
}

inline Signal signals_bad(const Health& s, const HealthParams& p, double time_s) {
    if (s.has_system_status && s.system_status != 3 && s.system_status != 4) return Signal::system_status;
    if (s.attitude_ok == -1 && !status_missing(s, p, time_s)) return Signal::no_status_yet;
    if (s.attitude_ok == 0) return Signal::attitude_not_ok;
    if (p.require_horiz_pos_ok && s.horiz_pos_ok == 0) return Signal::horiz_pos_lost;
    return Signal::none;
}

inline const char* signal_text(Signal sig, long system_status) {
    switch (sig) {
        case Signal::system_status: return intern("FC system_status " + std::to_string(system_status));
        case Signal::no_status_yet: return "no FC estimator status yet";
        case Signal::attitude_not_ok: return "FC EKF attitude not ok";
        case Signal::horiz_pos_lost: return "FC EKF horizontal position lost (GNSS)";
        default: return "";
    }
}

inline void clear_anchors(Health& s) {
    if (!s.anchors->empty()) s.anchors = std::make_shared<const std::vector<Anchor>>();
}

inline void health_on_attitude(Health& s, const M3& C_fc, const M3& C_g, double time_s, const HealthParams& p,
                               double gyro_var) {
    for (double v : C_fc) if (!std::isfinite(v)) throw std::invalid_argument("health_on_attitude: non-finite input");
    for (double v : C_g) if (!std::isfinite(v)) throw std::invalid_argument("health_on_attitude: non-finite input");
    if (!std::isfinite(time_s)) throw std::invalid_argument("health_on_attitude: non-finite input");
    if (s.has_fc_time && 0.0 < time_s - s.fc_time_s && time_s - s.fc_time_s < p.window_s) {
        const double step = time_s - s.fc_time_s;
        s.attitude_interval_s = !s.has_interval ? step : s.attitude_interval_s + INTERVAL_AVERAGING * (step - s.attitude_interval_s);
        s.has_interval = true;
    }
    if (!s.has_first_attitude) {
        s.has_first_attitude = true;
        s.first_attitude_s = time_s;
    }
    if (s.has_check_time && 0.0 <= time_s - s.check_time_s && time_s - s.check_time_s < p.check_period_s &&
        signals_bad(s, p, time_s) == Signal::none) {
        s.has_fc_time = true;
        s.fc_time_s = time_s;
        return;
    }
    double worst = 0.0;
    for (const Anchor& a : *s.anchors) {
        const M3 predicted = mm<3, 3, 3>(mm<3, 3, 3>(a.C_fc, tr<3, 3>(a.C_g)), C_g);
        const M3 D = mm<3, 3, 3>(C_fc, tr<3, 3>(predicted));
        const double d0 = 0.5 * (D[7] - D[5]), d1 = 0.5 * (D[2] - D[6]), d2 = 0.5 * (D[3] - D[1]);
        const double drift2 = std::pow(p.sigma_bias_rad_s * (time_s - a.t_a), 2) + std::max(0.0, gyro_var - a.v_a);
        const double thr_tilt = p.n_sigma * std::sqrt(2.0 * std::pow(p.sigma_fc_tilt_rad, 2) + drift2) + p.margin_rad;
        const double thr_yaw = p.n_sigma * std::sqrt(2.0 * std::pow(p.sigma_fc_yaw_rad, 2) + drift2) + p.margin_rad;
        const double r1 = std::hypot(d0, d1) / thr_tilt, r2 = std::fabs(d2) / thr_yaw;
        // max(worst, r1, r2): the first of equals, as Python's max
        double m = worst;
        if (r1 > m) m = r1;
        if (r2 > m) m = r2;
        worst = m;
    }
    const bool diverged = worst > 1.0;
    const Signal signals = signals_bad(s, p, time_s);
    const bool bad = signals != Signal::none;
    std::vector<Anchor> kept;
    kept.reserve(s.anchors->size() + 1);
    for (const Anchor& a : *s.anchors)
        if (time_s - a.t_a <= p.window_s) kept.push_back(a);
    if (diverged || bad || s.silent_divergence) {
        kept.clear();  // re-lay after the reference recovers
    } else if (kept.empty() || time_s - kept.back().t_a >= p.anchor_period_s) {
        kept.push_back(Anchor{time_s, C_fc, C_g, gyro_var});
    }
    if (kept.size() != s.anchors->size() || (!kept.empty() && kept.back().t_a != s.anchors->back().t_a) ||
        (!kept.empty() && kept.front().t_a != s.anchors->front().t_a))
        s.anchors = std::make_shared<const std::vector<Anchor>>(std::move(kept));
    const bool silent = (s.silent_divergence || (diverged && !bad)) && !bad;
    const bool good = !(diverged || bad || silent);
    if (good) {
        if (!s.has_good_since) { s.has_good_since = true; s.good_since_s = time_s; }
    } else {
        s.has_good_since = false;
    }
    // waiting for the first status is no loss: trusted at once when it says good (no re-trust hold)
    bool latched = s.latched_out || diverged || (bad && signals != Signal::no_status_yet) || silent;
    if (latched && good && time_s - s.good_since_s >= p.retrust_hold_s) latched = false;
    s.has_fc_time = true;
    s.fc_time_s = time_s;
    s.has_check_time = true;
    s.check_time_s = time_s;
    s.max_discrepancy_rad = worst;
    s.diverged = diverged || silent;
    s.silent_divergence = silent;
    s.latched_out = latched;
    s.ever_trusted = s.ever_trusted || (good && !latched);
    s.reason = bad ? signal_text(signals, s.system_status)
                   : (diverged || silent) ? "FC attitude disagrees with gyros"
                   : latched ? "re-trust hold" : "";
}

// health_trusted: (trusted, reason); the reason as a code (+ the number it quotes)
enum class TrustReason { trusted, no_attitude, too_slow, stale, signals, disagrees, retrust_hold, text };

struct Trust {
    TrustReason why = TrustReason::no_attitude;
    Signal signal = Signal::none;
    double value = 0.0;  // the interval (too_slow), the age (stale), the system_status (signals)
    const char* text = "";  // why == text: a reason taken over from a reference state as worded
    bool trusted() const { return why == TrustReason::trusted; }
};

// health_trusted's reason, worded as the reference words it
inline std::string trust_text(const Trust& t, const HealthParams& p) {
    char buf[160];
    switch (t.why) {
        case TrustReason::trusted: return "";
        case TrustReason::no_attitude: return "no FC attitude yet";
        case TrustReason::too_slow:
            std::snprintf(buf, sizeof buf, "FC ATTITUDE every %.2f s (> %g s): too slow to be a reference", t.value,
                          p.max_attitude_age_s);
            return buf;
        case TrustReason::stale:
            std::snprintf(buf, sizeof buf, "FC attitude stale (%.2f s)", t.value);
            return buf;
        case TrustReason::signals: return signal_text(t.signal, static_cast<long>(t.value));
        case TrustReason::disagrees: return "FC attitude disagrees with gyros";
        case TrustReason::retrust_hold: return "re-trust hold";
        default: return t.text;
    }
}

inline Trust health_trusted(const Health& s, double time_s, const HealthParams& p) {
    if (!s.has_fc_time) return {TrustReason::no_attitude};
    if (s.has_interval && s.attitude_interval_s > p.max_attitude_age_s)
        return {TrustReason::too_slow, Signal::none, s.attitude_interval_s};
    if (time_s - s.fc_time_s > p.max_attitude_age_s) return {TrustReason::stale, Signal::none, time_s - s.fc_time_s};
    const Signal sig = signals_bad(s, p, time_s);
    if (sig != Signal::none) return {TrustReason::signals, sig, static_cast<double>(s.system_status)};
    if (s.diverged) return {TrustReason::disagrees};
    if (s.latched_out) return {TrustReason::retrust_hold};
    return {TrustReason::trusted};
}

}  // namespace azimuthd
