// Flight phases, boot -> pre-launch -> launch -> in-flight: the compiled twin of
// service/phases.py phase_step (which stays the reference and holds the rules and their reasons;
// tests/test_core_phases.py proves them equal). What it calls is here too: the still blocks'
// levelling verdicts (estimators/levelling.py levelling_result, levelling_merge) on the rest
// accumulator of core/levelling.hpp, the started-in-flight rule, impulse / sustained take-off, the
// runway's airborne test, the disarmed refusal.
//
// Every scalar expression is the reference's, in its order (no FMA contraction: CMakeLists.txt).
// Events are (kind, text) pairs worded exactly as the reference words them: C printf's %.Nf is
// correctly rounded as Python's format is; the thresholds Python prints with :g come in as the
// texts Python made of them (Params::t_*), so no C %g is trusted to equal Python's.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "levelling.hpp"

namespace azimuthd {
namespace phases {

constexpr double STANDARD_GRAVITY_M_S2 = 9.80665;
constexpr double RAD_TO_DEG = 180.0 / M_PI;  // math.degrees / np.degrees: x * (180 / pi)
constexpr double DEG_TO_RAD = M_PI / 180.0;  // math.radians: x * (pi / 180)

enum Phase { BOOT = 0, PRE_LAUNCH = 1, LAUNCH = 2, IN_FLIGHT = 3 };
inline const char* phase_name(int p) {
    static const char* names[] = {"boot", "pre-launch", "launch", "in-flight"};
    return names[p];
}
enum Vehicle { NO_VEHICLE = -1, LAUNCHER = 0, HAND = 1, RUNWAY = 2, MULTICOPTER = 3, VTOL = 4 };

// Python's float formatting for one value: printf's (correctly rounded, as Python's), with
// Python's words for the non-finite ("nan" whatever its sign bit, "inf").
inline std::string fmt(const char* spec, double x) {
    if (std::isnan(x)) return (spec[1] == '+') ? "+nan" : "nan";
    if (std::isinf(x)) return x > 0 ? ((spec[1] == '+') ? "+inf" : "inf") : "-inf";
    char buf[64];
    std::snprintf(buf, sizeof buf, spec, x);
    return buf;
}
inline std::string fmt_int(double n) {  // a count held in a double (exact below 2^53)
    char buf[32];
    std::snprintf(buf, sizeof buf, "%lld", static_cast<long long>(n));
    return buf;
}

// estimators.levelling.LevellingParams, with Python's texts of the thresholds it prints
struct LevParams {
    double min_samples = 200, min_duration_s = 0.5, max_accel_std_m_s2 = 3.0, max_gyro_std_rad_s = 0.0,
           max_tilt_noise_rad = 0.0, max_gyro_sem_rad_s = 0.0, batch_s = 0.25, min_batches = 4,
           gravity_tolerance_m_s2 = 0.8, accel_bias_sigma_m_s2 = 0.1;
    std::string t_min_samples, t_min_duration_s, t_max_accel_std_m_s2, t_max_gyro_std_deg, t_max_tilt_noise_deg,
        t_max_gyro_sem_deg;
};

// service.phases.PhaseParams (+ its InFlightParams), with Python's texts of what it prints with :g
struct Params {
    double still_seconds = 2.0, detect_accel_m_s2 = 5.0, detect_hold_s = 0.05, boost_window_s = 1.0;
    LevParams lev, lev_short;  // lev_short: the short rest of a launch before any levelling
    double airspeed_m_s = 12.0, alt_rate_m_s = 1.5, hold_s = 1.0, not_still_s = 4.0, accel_norm_m_s2 = 2.0,
           accel_norm_hold_s = 1.0, decide_s = 4.5;
    int vehicle = LAUNCHER;
    std::string vehicle_name;
    double fwd[3] = {1.0, 0.0, 0.0};
    bool detect_started_in_flight = true;
    double filter_tau_s = 0.2, runway_accel_m_s2 = 1.5, runway_hold_s = 1.0, runway_max_roll_s = 60.0,
           liftoff_accel_m_s2 = 0.8, liftoff_hold_s = 0.3, liftoff_climb_m_s = 0.7, impulse_forward_share = 0.5,
           moved_rad = 0.0;
    std::string t_airspeed_m_s, t_alt_rate_m_s, t_accel_norm_m_s2, t_detect_accel_m_s2, t_runway_accel_m_s2,
        t_liftoff_accel_m_s2, t_liftoff_climb_m_s, t_runway_max_roll_s;
};

// service.phases.FlightEvidence: tri-states (-1 None or not a bool, 0 False, 1 True: the reference
// asks `is True` / `is False`); NaN for a number that is None (every test on it is then false, as
// the reference's `is not None and ...`)
struct Evidence {
    int armed = -1, fc_reports_flying = -1, fc_landed = -1;
    double airspeed_m_s = NAN, alt_rate_m_s = NAN;
};

// estimators.levelling.LevellingResult; `why` is the reason's form (its text: reason_text)
enum Why { OK = 0, FEW_SAMPLES, TOO_SHORT, ACCEL_MOVING, GYRO_MOVING, TILT_NOISE, GYRO_SEM, NOT_GRAVITY };
struct LevResult {
    bool ok = false;
    int why = FEW_SAMPLES;
    double roll_rad = NAN, pitch_rad = NAN;
    double gyro_bias_rad_s[3] = {0, 0, 0}, accel_mean_m_s2[3] = {0, 0, 0};  // only with ok
    double roll_sigma_rad = NAN, pitch_sigma_rad = NAN;
    double samples = 0, duration_s = NAN, accel_std_m_s2 = NAN, tilt_noise_rad = NAN,
           gyro_bias_sigma_rad_s = NAN;
    bool noisy = false;
    double max_gyro_std_rad_s = NAN, norm_m_s2 = NAN;  // figures of the reasons
};

inline double npmax3(const double v[3]) {  // np.max: NaN if any is NaN
    double m = v[0];
    for (int i = 0; i < 3; ++i) {
        if (std::isnan(v[i])) return NAN;
        if (v[i] > m) m = v[i];
    }
    return m;
}
inline double npmaximum(double a, double b) {  // np.maximum: NaN propagates
    if (std::isnan(a) || std::isnan(b)) return NAN;
    return a > b ? a : b;
}
inline double norm3(const double v[3]) { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }
inline double dot3(const double a[3], const double b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

// estimators.levelling.levelling_result
inline LevResult levelling_result(const LevellingAcc& s, const LevParams& p) {
    LevResult r;
    const double n = s.n;
    const double dur = s.timed ? s.t_last_s - s.t_first_s : NAN;
    r.samples = n;
    r.duration_s = dur;
    if (n < (p.min_samples > 2 ? p.min_samples : 2.0)) { r.why = FEW_SAMPLES; return r; }
    if (std::isfinite(dur) && dur < p.min_duration_s) { r.why = TOO_SHORT; return r; }
    double accel_std[3], gyro_std[3], sem_a[3], sem_g[3];
    for (int i = 0; i < 3; ++i) {
        accel_std[i] = std::sqrt(s.accel_m2[i] / (n - 1));
        gyro_std[i] = std::sqrt(s.gyro_m2[i] / (n - 1));
        sem_a[i] = std::sqrt(s.accel_m2[i] / (n - 1) / n);
        sem_g[i] = std::sqrt(s.gyro_m2[i] / (n - 1) / n);
    }
    if (s.nb >= p.min_batches) {
        const double nb = s.nb;
        for (int i = 0; i < 3; ++i) {
            sem_a[i] = npmaximum(sem_a[i], std::sqrt(s.batch_accel_m2[i] / (nb - 1) / nb));
            sem_g[i] = npmaximum(sem_g[i], std::sqrt(s.batch_gyro_m2[i] / (nb - 1) / nb));
        }
    }
    const double* f = s.accel_mean_m_s2;
    const double norm = norm3(f);
    const double tilt_noise = std::sqrt(sem_a[0] * sem_a[0] + sem_a[1] * sem_a[1]) / (1e-9 > norm ? 1e-9 : norm);  // Python's max(norm, 1e-9)
    r.accel_std_m_s2 = npmax3(accel_std);
    r.tilt_noise_rad = tilt_noise;
    r.gyro_bias_sigma_rad_s = npmax3(sem_g);
    r.max_gyro_std_rad_s = npmax3(gyro_std);
    r.norm_m_s2 = norm;
    if (r.accel_std_m_s2 > p.max_accel_std_m_s2) { r.why = ACCEL_MOVING; return r; }
    if (r.max_gyro_std_rad_s > p.max_gyro_std_rad_s) { r.why = GYRO_MOVING; return r; }
    if (tilt_noise > p.max_tilt_noise_rad) { r.why = TILT_NOISE; r.noisy = true; return r; }
    if (r.gyro_bias_sigma_rad_s > p.max_gyro_sem_rad_s) { r.why = GYRO_SEM; r.noisy = true; return r; }
    if (std::fabs(norm - STANDARD_GRAVITY_M_S2) > p.gravity_tolerance_m_s2) { r.why = NOT_GRAVITY; return r; }
    r.ok = true;
    r.why = OK;
    r.roll_rad = std::atan2(-f[1], -f[2]);
    r.pitch_rad = std::atan2(f[0], std::hypot(f[1], f[2]));
    const double tilt_sigma = std::hypot(tilt_noise, p.accel_bias_sigma_m_s2 / norm);
    r.roll_sigma_rad = r.pitch_sigma_rad = tilt_sigma;
    for (int i = 0; i < 3; ++i) {
        r.gyro_bias_rad_s[i] = s.gyro_mean_rad_s[i];
        r.accel_mean_m_s2[i] = f[i];
    }
    return r;
}

// LevellingResult.reason
inline std::string reason_text(const LevResult& r, const LevParams& p) {
    const double n = r.samples, dur = r.duration_s;
    switch (r.why) {
        case OK: return "";
        case FEW_SAMPLES: {
            std::string rate;
            if (std::isfinite(dur) && dur > 0) rate = " in " + fmt("%.1f", dur) + " s (" + fmt("%.0f", n / dur) + " Hz)";
            return fmt_int(n) + " of " + p.t_min_samples + " still samples" + rate;
        }
        case TOO_SHORT: return fmt("%.2f", dur) + " s of " + p.t_min_duration_s + " s of still samples";
        case ACCEL_MOVING:
            return "accelerometer not still: moving (std " + fmt("%.3f", r.accel_std_m_s2) + " m/s^2 > " +
                   p.t_max_accel_std_m_s2 + ")";
        case GYRO_MOVING:
            return "gyro not still: moving (std " + fmt("%.3f", r.max_gyro_std_rad_s * RAD_TO_DEG) + " deg/s > " +
                   p.t_max_gyro_std_deg + ")";
        case TILT_NOISE:
            return "accelerometer not still: its mean gives a tilt noise of " + fmt("%.2f", r.tilt_noise_rad * RAD_TO_DEG) +
                   " deg > " + p.t_max_tilt_noise_deg + " deg (std " + fmt("%.2f", r.accel_std_m_s2) + " m/s^2)";
        case GYRO_SEM:
            return "gyro not still: its mean is uncertain by " + fmt("%.3f", r.gyro_bias_sigma_rad_s * RAD_TO_DEG) +
                   " deg/s > " + p.t_max_gyro_sem_deg + " deg/s";
        default: return "|f| = " + fmt("%.2f", r.norm_m_s2) + " m/s^2 is not gravity";
    }
}

// LevellingResult.figures()
inline std::string figures_text(const LevResult& r) {
    std::string out = fmt_int(r.samples) + " samples";
    if (std::isfinite(r.duration_s) && r.duration_s > 0)
        out += " (" + fmt("%.0f", r.samples / r.duration_s) + " Hz over " + fmt("%.1f", r.duration_s) + " s)";
    if (std::isfinite(r.accel_std_m_s2)) out += ", accel std " + fmt("%.2f", r.accel_std_m_s2) + " m/s^2";
    if (std::isfinite(r.tilt_noise_rad)) out += ", tilt noise " + fmt("%.2f", r.tilt_noise_rad * RAD_TO_DEG) + " deg";
    if (std::isfinite(r.gyro_bias_sigma_rad_s))
        out += ", gyro bias sigma " + fmt("%.3f", r.gyro_bias_sigma_rad_s * RAD_TO_DEG) + " deg/s";
    return out;
}

// service.phases._level_text
inline std::string level_text(const LevResult& r) {
    return "roll " + fmt("%.2f", r.roll_rad * RAD_TO_DEG) + " deg, pitch " + fmt("%.2f", r.pitch_rad * RAD_TO_DEG) +
           " deg (" + figures_text(r) + ")";
}

// estimators.levelling._chan for one 3-vector pair: mean and m2 of a then b
inline void chan3(double n_a, const double mean_a[3], const double m2_a[3], double n_b, const double mean_b[3],
                  const double m2_b[3], double mean[3], double m2[3]) {
    const double n = n_a + n_b;
    const double w = n_b / n, c = n_a * n_b / n;
    for (int i = 0; i < 3; ++i) {
        const double d = mean_b[i] - mean_a[i];
        mean[i] = mean_a[i] + d * w;
        m2[i] = m2_a[i] + m2_b[i] + d * d * c;
    }
}

// estimators.levelling.levelling_merge (a before b)
inline LevellingAcc levelling_merge(const LevellingAcc& a, const LevellingAcc& b) {
    if (a.n == 0) return b;
    if (b.n == 0) return a;
    LevellingAcc m = b;  // b's open batch
    m.n = a.n + b.n;
    chan3(a.n, a.accel_mean_m_s2, a.accel_m2, b.n, b.accel_mean_m_s2, b.accel_m2, m.accel_mean_m_s2, m.accel_m2);
    chan3(a.n, a.gyro_mean_rad_s, a.gyro_m2, b.n, b.gyro_mean_rad_s, b.gyro_m2, m.gyro_mean_rad_s, m.gyro_m2);
    if (a.nb != 0 && b.nb != 0) {
        chan3(a.nb, a.batch_accel_mean, a.batch_accel_m2, b.nb, b.batch_accel_mean, b.batch_accel_m2,
              m.batch_accel_mean, m.batch_accel_m2);
        chan3(a.nb, a.batch_gyro_mean, a.batch_gyro_m2, b.nb, b.batch_gyro_mean, b.batch_gyro_m2,
              m.batch_gyro_mean, m.batch_gyro_m2);
        m.nb = a.nb + b.nb;
        m.has_stats = true;
    } else if (a.nb != 0) {
        m.nb = a.nb;
        m.has_stats = a.has_stats;
        for (int i = 0; i < 3; ++i) {
            m.batch_accel_mean[i] = a.batch_accel_mean[i];
            m.batch_accel_m2[i] = a.batch_accel_m2[i];
            m.batch_gyro_mean[i] = a.batch_gyro_mean[i];
            m.batch_gyro_m2[i] = a.batch_gyro_m2[i];
        }
    }
    m.timed = a.timed || b.timed;
    m.t_first_s = a.timed ? a.t_first_s : b.t_first_s;
    m.t_last_s = b.timed ? b.t_last_s : a.t_last_s;
    return m;
}

using Opt = std::optional<double>;

// service.phases.PhaseState
struct State {
    int phase = BOOT;
    LevellingAcc block;
    Opt block_start_s;
    std::optional<LevResult> level;
    std::optional<LevellingAcc> level_block;
    Opt level_time_s, above_since_s, below_since_s, launch_time_s;
    std::string launch_evidence;
    Opt start_time_s;
    bool started_in_flight = false;
    std::string in_flight_evidence;
    Opt airspeed_since_s, fc_flying_since_s, alt_rate_since_s, accel_norm_since_s, fc_air_since_s;
    bool fc_seen_landed = false;
    double not_still_total_s = 0.0;
    std::optional<LevResult> pending_level;
    std::optional<LevellingAcc> pending_block;
    LevellingAcc noisy_run;
    Opt block_passed_s;
    bool has_last_block_mean = false;
    double last_block_mean_m_s2[3] = {0, 0, 0};
    Opt time_prev_s;
    bool has_f_lp = false;
    double f_lp_m_s2[3] = {0, 0, 0};
    Opt run_since_s, climb_since_s;
    double impulse_sum_m_s2[3] = {0, 0, 0};
    bool impulse_refused = false, disarmed_refused = false;
    double moved_vec_rad[3] = {0, 0, 0};
    double moved_rad = 0.0;
    unsigned long level_version = 0;  // counts changes of level / level_block (the Python face's cache)
};

using Events = std::vector<std::pair<const char*, std::string>>;

inline bool deciding(const State& s, double t, const Evidence& ev, const Params& p) {
    return ev.armed == 1 && !s.level && s.start_time_s && t - *s.start_time_s < p.decide_s;
}

inline Opt since(const Opt& prev, bool cond, double t) { return cond ? (prev ? prev : Opt(t)) : Opt(); }

// service.phases._in_flight_evidence: the evidence timers; the evidence that the vehicle flies ("" = none)
inline std::string in_flight_evidence(State& s, double excess, double t, const Evidence& ev, const Params& p) {
    s.airspeed_since_s = since(s.airspeed_since_s, ev.airspeed_m_s > p.airspeed_m_s, t);
    s.fc_flying_since_s = since(s.fc_flying_since_s, ev.fc_reports_flying == 1, t);
    s.alt_rate_since_s = since(s.alt_rate_since_s, std::fabs(ev.alt_rate_m_s) > p.alt_rate_m_s, t);
    s.accel_norm_since_s = since(s.accel_norm_since_s, excess > p.accel_norm_m_s2, t);
    if (ev.armed != 1) return "";
    std::vector<std::string> found;
    if (s.fc_flying_since_s && t - *s.fc_flying_since_s >= p.hold_s)
        found.push_back("the FC reports flying (HEARTBEAT MAV_STATE_ACTIVE from ArduPlane)");
    if (!s.fc_seen_landed && s.fc_air_since_s && t - *s.fc_air_since_s >= p.hold_s)
        found.push_back("the FC reports in the air (landed state)");
    if (s.airspeed_since_s && t - *s.airspeed_since_s >= p.hold_s)
        found.push_back("airspeed " + fmt("%.1f", ev.airspeed_m_s) + " m/s > " + p.t_airspeed_m_s + " m/s");
    if (s.alt_rate_since_s && t - *s.alt_rate_since_s >= p.hold_s)
        found.push_back("baro altitude rate " + fmt("%+.1f", ev.alt_rate_m_s) + " m/s beyond " + p.t_alt_rate_m_s + " m/s");
    if (s.not_still_total_s >= p.not_still_s) found.push_back("IMU not still for " + fmt("%.1f", s.not_still_total_s) + " s");
    if (s.accel_norm_since_s && t - *s.accel_norm_since_s >= p.accel_norm_hold_s)
        found.push_back("| |f| - g | = " + fmt("%.1f", excess) + " m/s^2 > " + p.t_accel_norm_m_s2 + " m/s^2 for " +
                        fmt("%.1f", t - *s.accel_norm_since_s) + " s");
    if (found.empty()) return "";
    std::string why = "FC armed, ";
    for (size_t i = 0; i < found.size(); ++i) why += (i ? ", " : "") + found[i];
    return why;
}

// service.phases._track: the low-passed specific force, the FC's landed state, the rotation since
// the kept levelling block
inline void track(State& s, const double g[3], const double a[3], double t, const Evidence& ev, const Params& p) {
    const double dt = s.time_prev_s ? t - *s.time_prev_s : 0.0;
    const bool in_dt = 0.0 < dt && dt < 1.0;
    if (!s.has_f_lp || !in_dt) {
        for (int i = 0; i < 3; ++i) s.f_lp_m_s2[i] = a[i];
    } else {
        const double k = dt / (p.filter_tau_s + dt);
        for (int i = 0; i < 3; ++i) s.f_lp_m_s2[i] = s.f_lp_m_s2[i] + (a[i] - s.f_lp_m_s2[i]) * k;
    }
    s.has_f_lp = true;
    s.fc_seen_landed = s.fc_seen_landed || ev.fc_landed == 1;
    s.fc_air_since_s = (ev.fc_landed == 0) ? (s.fc_air_since_s ? s.fc_air_since_s : Opt(t)) : Opt();
    if (s.level && in_dt) {
        const double* b = s.level->gyro_bias_rad_s;
        for (int i = 0; i < 3; ++i) s.moved_vec_rad[i] = s.moved_vec_rad[i] + (g[i] - b[i]) * dt;
        const double m = std::sqrt(s.moved_vec_rad[0] * s.moved_vec_rad[0] + s.moved_vec_rad[1] * s.moved_vec_rad[1] +
                                   s.moved_vec_rad[2] * s.moved_vec_rad[2]);
        if (m > s.moved_rad) s.moved_rad = m;  // Python's max(moved, m)
    }
    s.time_prev_s = t;
}

// service.phases._reference_f: the specific force at rest (nullptr: none yet)
inline const double* reference_f(const State& s) {
    if (s.level) return s.level->accel_mean_m_s2;
    return s.has_last_block_mean ? s.last_block_mean_m_s2 : nullptr;
}

// service.phases._sustained_takeoff: runway roll / lift-off; the launch time (none: no launch) and why
inline Opt sustained_takeoff(State& s, double t, const Evidence& ev, const Params& p, std::string& why) {
    const double* ref = reference_f(s);
    Opt launch;
    if (ref && s.has_f_lp) {
        const double g_ref = norm3(ref);
        double up[3], d[3];
        for (int i = 0; i < 3; ++i) {
            up[i] = ref[i] / g_ref;
            d[i] = s.f_lp_m_s2[i] - ref[i];
        }
        const double vert = dot3(d, up);
        double value, thr, hold;
        const char* what;
        const std::string* t_thr;
        if (p.vehicle == RUNWAY) {
            const double fu = dot3(p.fwd, up);
            double fwd_h[3];
            for (int i = 0; i < 3; ++i) fwd_h[i] = p.fwd[i] - fu * up[i];
            const double nh = norm3(fwd_h);
            value = nh > 0.1 ? dot3(d, fwd_h) / nh : 0.0;
            thr = p.runway_accel_m_s2, hold = p.runway_hold_s, what = "forward", t_thr = &p.t_runway_accel_m_s2;
        } else {
            value = vert, thr = p.liftoff_accel_m_s2, hold = p.liftoff_hold_s, what = "vertical",
            t_thr = &p.t_liftoff_accel_m_s2;
        }
        s.run_since_s = since(s.run_since_s, value > thr, t);
        if (s.run_since_s && t - *s.run_since_s >= hold) {
            launch = *s.run_since_s - p.filter_tau_s;  // the low-pass crossed its threshold about tau late
            why = std::string(what) + " specific force " + fmt("%+.1f", value) + " m/s^2 > " + *t_thr + " m/s^2 for " +
                  fmt("%.1f", t - *s.run_since_s) + " s";
        }
    }
    if (!launch && (p.vehicle == MULTICOPTER || p.vehicle == VTOL)) {
        s.climb_since_s = since(s.climb_since_s, ev.alt_rate_m_s > p.liftoff_climb_m_s, t);
        if (s.climb_since_s && t - *s.climb_since_s >= p.hold_s) {
            launch = s.climb_since_s;
            why = "baro climb " + fmt("%+.1f", ev.alt_rate_m_s) + " m/s > " + p.t_liftoff_climb_m_s + " m/s";
        }
    }
    return launch;
}

// service.phases._impulse_takeoff: launcher boost / hand throw, pointing forward
inline Opt impulse_takeoff(State& s, const double a[3], double excess, double t, const Params& p, std::string& why,
                           Events& events) {
    if (excess <= p.detect_accel_m_s2) {
        if (s.above_since_s || s.impulse_refused) {
            s.above_since_s.reset();
            for (double& v : s.impulse_sum_m_s2) v = 0.0;
            s.impulse_refused = false;
        }
        return Opt();
    }
    const double since_s = s.above_since_s ? *s.above_since_s : t;
    const double* ref = reference_f(s);
    for (int i = 0; i < 3; ++i) s.impulse_sum_m_s2[i] = s.impulse_sum_m_s2[i] + (ref ? a[i] - ref[i] : a[i]);
    s.above_since_s = since_s;
    if (t - since_s < p.detect_hold_s || s.impulse_refused) return Opt();
    const double n = norm3(s.impulse_sum_m_s2);
    const double share = n > 0 ? dot3(s.impulse_sum_m_s2, p.fwd) / n : 0.0;
    if (share < p.impulse_forward_share) {
        events.emplace_back("takeoff_refused", "specific-force spike |f| = " + fmt("%.0f", norm3(a)) + " m/s^2 pointing " +
                                                   (share < 0 ? "backward" : "off the flight axis") + " (forward share " +
                                                   fmt("%+.2f", share) +
                                                   "): not a take-off (an impact, a knock or a pick-up)");
        s.impulse_refused = true;
        return Opt();
    }
    why = "| |f| - g | " + fmt("%.1f", excess) + " m/s^2 > " + p.t_detect_accel_m_s2 + " m/s^2 forward";
    return since_s;
}

inline void reset_moved(State& s) {
    for (double& v : s.moved_vec_rad) v = 0.0;
    s.moved_rad = 0.0;
}

inline void keep_level(State& s, const LevResult& res, const LevellingAcc& block, double t) {
    s.level = res;
    s.level_block = block;
    s.level_time_s = t;
    s.pending_level.reset();
    s.pending_block.reset();
    reset_moved(s);
    ++s.level_version;
}

// service.phases._take_level: a passing block against the kept levelling (copies taken: res and
// block may be the state's own pending ones)
inline void take_level(State& s, const LevResult res, const LevellingAcc block, double t, Events& events) {
    if (!s.level) {
        events.emplace_back("levelled", level_text(res));
        keep_level(s, res, block, t);
        return;
    }
    const LevResult& cur = *s.level;
    const double* a = cur.accel_mean_m_s2;
    const double* b = res.accel_mean_m_s2;
    double c = dot3(a, b) / (norm3(a) * norm3(b));
    c = std::max(-1.0, std::min(1.0, c));
    const double tilt_change = std::acos(c);
    const double noise = std::hypot(cur.tilt_noise_rad, res.tilt_noise_rad);
    if (tilt_change > 3.0 * noise + 0.05 * DEG_TO_RAD) {  // moved or set down: the new attitude counts
        events.emplace_back("levelled", "again, the tilt changed by " + fmt("%.2f", tilt_change * RAD_TO_DEG) +
                                            " deg: " + level_text(res));
    } else if (!(res.gyro_bias_sigma_rad_s < cur.gyro_bias_sigma_rad_s)) {  // same attitude, noisier: keep
        reset_moved(s);
        return;
    }
    keep_level(s, res, block, t);
}

// service.phases._launch: take-off decided at launch_s
inline void launch(State& s, double launch_s, const std::string& why, double t, const Params& p, Events& events) {
    if (!s.level && s.pending_level) take_level(s, *s.pending_level, *s.pending_block, t, events);
    if (!s.level) {
        const LevResult res = levelling_result(s.block, p.lev_short);
        if (res.ok) {
            s.level = res;
            s.level_block = s.block;
            s.level_time_s = t;
            ++s.level_version;
            events.emplace_back("levelled", "on a short rest: " + level_text(res));
        } else {
            events.emplace_back("launch_unlevelled", "launch before any levelling (" + reason_text(res, p.lev_short) +
                                                         "); attitude from the attitude filter only");
        }
    }
    s.phase = LAUNCH;
    s.launch_time_s = launch_s;
    s.launch_evidence = why;
    s.below_since_s.reset();
    events.emplace_back("takeoff", p.vehicle_name + ": " + why + ", at " + fmt("%.2f", launch_s) + " s");
    events.emplace_back("phase", "launch");
}

// service.phases.phase_step: one IMU sample
inline void phase_step(State& s, const double g[3], const double a[3], double t, const Params& p, const Evidence& ev,
                       Events& events) {
    const double excess = std::fabs(std::sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) - STANDARD_GRAVITY_M_S2);
    const bool above = excess > p.detect_accel_m_s2;
    const bool impulse = p.vehicle == LAUNCHER || p.vehicle == HAND;

    if (s.phase == BOOT) {
        s.phase = PRE_LAUNCH;
        s.block_start_s = t;
        s.start_time_s = t;
        events.emplace_back("phase", "pre-launch");
    }
    if (s.phase == PRE_LAUNCH || s.phase == LAUNCH) track(s, g, a, t, ev, p);

    if (s.phase == PRE_LAUNCH && !s.level && p.detect_started_in_flight) {
        const std::string why = in_flight_evidence(s, excess, t, ev, p);
        if (!why.empty()) {
            s.phase = IN_FLIGHT;
            s.started_in_flight = true;
            s.in_flight_evidence = why;
            s.block = LevellingAcc();
            s.above_since_s.reset();
            s.pending_level.reset();
            s.pending_block.reset();
            events.emplace_back("started_in_flight", why + ": no levelling, no launch");
            events.emplace_back("phase", "in-flight");
            return;
        }
    }

    if (s.phase == PRE_LAUNCH && s.pending_level && !deciding(s, t, ev, p))  // the decision window is over
        take_level(s, *s.pending_level, *s.pending_block, t, events);

    if (s.phase == PRE_LAUNCH) {
        Opt launch_s;
        std::string why;
        if (p.vehicle == NO_VEHICLE) {
        } else if (impulse) {
            launch_s = impulse_takeoff(s, a, excess, t, p, why, events);
        } else {
            launch_s = sustained_takeoff(s, t, ev, p, why);
        }
        if (!launch_s && p.vehicle != NO_VEHICLE && s.fc_seen_landed && s.fc_air_since_s &&
            t - *s.fc_air_since_s >= p.hold_s) {
            launch_s = s.fc_air_since_s;
            why = "the FC reports in the air after landed (landed state)";
        }
        if (launch_s && ev.armed == 0) {
            if (!s.disarmed_refused)
                events.emplace_back("takeoff_refused", why + " while the FC says disarmed: not a take-off");
            s.disarmed_refused = true;
            launch_s.reset();
        }
        if (launch_s) {
            launch(s, *launch_s, why, t, p, events);
            return;
        }
        if (impulse && above) return;  // a spike sample is neither rest data nor a launch yet
        levelling_step(s.block, g, a, t, p.lev.batch_s);
        const double start = s.block_start_s ? *s.block_start_s : t;
        if (t - start >= p.still_seconds) {
            LevResult res = levelling_result(s.block, p.lev);
            LevellingAcc block = s.block;
            s.has_last_block_mean = true;
            for (int i = 0; i < 3; ++i) s.last_block_mean_m_s2[i] = block.accel_mean_m_s2[i];
            if (!s.level) {  // the started-in-flight rule's stillness evidence
                const LevParams& lp = p.lev;
                const bool moving = !res.noisy || res.tilt_noise_rad > 3 * lp.max_tilt_noise_rad ||
                                    res.gyro_bias_sigma_rad_s > 3 * lp.max_gyro_sem_rad_s;
                const bool still_fail = !res.ok && block.n >= lp.min_samples && moving;
                s.not_still_total_s = still_fail ? s.not_still_total_s + (t - start) : 0.0;
            }
            if (res.noisy) {  // vibrating: try the longer window of the consecutive noisy blocks
                const LevellingAcc merged = levelling_merge(s.noisy_run, block);
                const LevResult res_m = levelling_result(merged, p.lev);
                s.noisy_run = res_m.noisy ? merged : LevellingAcc();
                if (res_m.ok || !res_m.noisy) {
                    res = res_m;
                    block = merged;
                }
            } else if (s.noisy_run.n != 0) {
                s.noisy_run = LevellingAcc();
            }
            if (res.ok) {
                s.block_passed_s = t;
                if (deciding(s, t, ev, p)) {  // held until the rule has its evidence
                    s.pending_level = res;
                    s.pending_block = block;
                } else {
                    take_level(s, res, block, t, events);
                }
            } else {
                std::string text = reason_text(res, p.lev);
                if (std::isfinite(res.accel_std_m_s2)) text += " (" + figures_text(res) + ")";  // else the reason has them
                events.emplace_back("not_still", text);
            }
            s.block = LevellingAcc();
            s.block_start_s = t;
        }
        return;
    }

    if (s.phase == LAUNCH) {
        bool over = false;
        if (impulse) {
            if (!above) {
                const double since_s = s.below_since_s ? *s.below_since_s : t;
                s.below_since_s = since_s;
                over = t - since_s >= p.detect_hold_s;
            } else {
                s.below_since_s.reset();
            }
            over = over || t - *s.launch_time_s >= p.boost_window_s;
        } else if (p.vehicle == RUNWAY) {
            std::string why;
            if (ev.fc_landed == 0 || ev.fc_reports_flying == 1)
                why = "the FC reports in the air";
            else if (ev.alt_rate_m_s > p.alt_rate_m_s)
                why = "baro climb " + fmt("%+.1f", ev.alt_rate_m_s) + " m/s";
            else if (t - *s.launch_time_s >= p.runway_max_roll_s)
                why = p.t_runway_max_roll_s + " s after the roll began";
            over = !why.empty();
            if (over)
                events.emplace_back("airborne", why + ", " + fmt("%.1f", t - *s.launch_time_s) + " s after the roll began");
        } else {
            over = t - *s.launch_time_s >= p.boost_window_s;
        }
        if (over) {
            s.phase = IN_FLIGHT;
            events.emplace_back("phase", "in-flight");
        }
    }
}

}  // namespace phases
}  // namespace azimuthd
