// Method B, variant b2, one event at a time (the compiled twin of estimators/synthetic_ahrs.py,
// which stays the reference and holds the derivations: KF2 integrates the gyros and fuses the
// magnetometer (KF1-corrected), the air-data roll/pitch and, while trusted, the FC attitude; KF1
// learns the magnetometer errors; the heading's sensitivity a to the FC's yaw error,
// a <- (1 - k) a + k on an FC update, a <- (1 - k) a on a magnetometer update; the bias revert on
// a detected loss). Each event runs on a copy of the state that replaces it only when the event
// completes: an event the reference refuses (ValueError) leaves the state as it was.
#pragma once

#include "ahrs_kf2.hpp"
#include "air_data.hpp"
#include "mag_error_kf.hpp"
#include "reference_health.hpp"

namespace azimuthd {

constexpr double G_M_S2 = 9.80665;

struct AhrsParams {
    bool mag_heading;  // mag_mode == "heading"
    M3 C_body_from_sensor;
    V3 field_nav_gauss;
    double fc_sigma_tilt_rad, fc_sigma_yaw_rad;
    bool use_fc_yaw;
    double ref_update_interval_s, mag_update_interval_s, air_update_interval_s;
    double air_roll_limit_rad, air_pitch_limit_rad, air_rate_limit_rad_s, air_sigma_roll_rad, air_sigma_pitch_rad,
        air_sigma_alt_rate_m_s, alpha_tau_s, rate_lp_tau_s, bias_revert_age_s, bias_snapshot_period_s,
        init_without_reference_s, init_sigma_tilt_rad, init_sigma_heading_rad;
    double field_model_sigma_rad;
    bool consider_mag_errors;
    double kf1_sigma_scale_init, kf1_sigma_cross_init;  // KF1's prior (P_c when no estimate is applied)
    AirParams air;
    Kf1Params kf1;
    Kf2Params kf2;
    HealthParams health;
};

struct Snapshot {
    double t;
    V3 b_g, b_m;
    Q4 q, q_free;
    P9 P;
};
using Snapshots = std::shared_ptr<const std::vector<Snapshot>>;

struct Ahrs {
    AirState air;
    bool has_air_last = false;
    AirOut air_last{};
    Health health;
    bool has_q_free = false;
    Q4 q_gyro_free{1, 0, 0, 0};
    bool has_gyro_prev = false;
    V3 gyro_prev_rad_s{0, 0, 0};
    double gyro_free_var_rad2 = 0.0;
    bool has_kf2 = false;
    Kf2 kf2;
    Kf1 kf1_learn;
    std::shared_ptr<const Kf1> kf1_applied;  // null: None
    bool has_k_alpha = false;
    double k_alpha_pa = 0.0;
    bool has_omega_lp = false;
    V3 omega_lp_rad_s{0, 0, 0};
    bool has_fc_last = false;
    double fc_last_t = 0.0;
    V3 fc_last_e{0, 0, 0};
    bool has_time = false;
    double time_s = 0.0;
    double last_mag_update_s = -INFINITY, last_air_update_s = -INFINITY, last_ref_update_s = -INFINITY;
    bool trusted = false;
    Trust trust;
    Snapshots snaps = std::make_shared<const std::vector<Snapshot>>();
    bool air_active = false;
    const char* air_off_reason = "no air data yet";
    bool kf1_learning = false;
    long n_kf1_rejected = 0;
    bool has_first_imu = false;
    double first_imu_time_s = 0.0;
    double ref_heading_sens = 0.0;
    bool reacquire_heading = false;
    double imu_integrated_s = 0.0;      // IMU intervals integrated (<= kf2.max_dt_s each) ...
    double imu_not_integrated_s = 0.0;  // ... and those held across (longer: a gap, inputs too slow)
};

inline V3 m3v(const M3& C, const V3& v) { return mv<3, 3>(C, v); }

inline bool kf1_applied_usable(const Ahrs& s) { return s.kf1_applied && s.kf1_applied->has_norm; }

inline void ahrs_trust(Ahrs& s, double time_s, const AhrsParams& p) {
    const Trust t = health_trusted(s.health, time_s, p.health);
    if (s.trusted && !t.trusted() && s.has_kf2) {
        // revert the gyro bias to a snapshot taken before the reference could have failed
        const Snapshot* old = nullptr;
        for (const Snapshot& sn : *s.snaps)
            if (time_s - sn.t >= p.bias_revert_age_s) old = &sn;
        if (old && s.health.silent_divergence && s.has_q_free) {
            // silent: also take back the attitude the failing reference pulled, re-propagating the
            // snapshot's attitude with our gyro-only increments since then
            const Q4 q = quat_mul(quat_mul(old->q, quat_conj(old->q_free)), s.q_gyro_free);
            // the snapshot's whole covariance goes with its attitude and biases (its attitude block
            // alone beside today's cross-covariances is no covariance), the attitude widened
            P9 P = old->P;
            const double v = 1.0 * std::pow(p.health.sigma_bias_rad_s * (time_s - old->t), 2);
            for (int i = 0; i < 3; ++i) P[i * KN + i] += v;
            s.kf2.gyro_bias_rad_s = old->b_g;
            s.kf2.mag_bias = old->b_m;
            s.kf2.q_nav_from_body = quat_unit(q);
            s.kf2.P = P;
        } else if (old) {
            s.kf2.gyro_bias_rad_s = old->b_g;
            s.kf2.mag_bias = old->b_m;
        }
    }
    s.trusted = t.trusted();
    s.trust = t;
}

// synthetic_ahrs._init_without_reference: KF2's heading from the magnetometer levelled with the
// FC's roll/pitch (FC trusted, its yaw not to be used) or level after init_without_reference_s:
// psi = atan2(B_E, B_N) - atan2(m_lev_y, m_lev_x)
inline void ahrs_init_without_reference(Ahrs& s, bool has_mag, const V3& mag_s, double t, const AhrsParams& p) {
    const bool fc_tilt = s.trusted && !p.use_fc_yaw && s.has_fc_last;
    if ((s.trusted && !fc_tilt) || !has_mag || (!fc_tilt && t - s.first_imu_time_s < p.init_without_reference_s))
        return;
    V3 m = m3v(p.C_body_from_sensor, mag_s);
    if (!finite3(m)) return;
    if (kf1_applied_usable(s)) m = kf1_correct_mag(*s.kf1_applied, m);
    const double roll = fc_tilt ? s.fc_last_e[0] : 0.0, pitch = fc_tilt ? s.fc_last_e[1] : 0.0;
    const V3 m_lev = m3v(dcm_from_euler(roll, pitch, 0.0), m);
    if (std::hypot(m_lev[0], m_lev[1]) <= 0.0) return;
    const V3& Bn = p.field_nav_gauss;
    const double psi = std::atan2(Bn[1], Bn[0]) - std::atan2(m_lev[1], m_lev[0]);
    s.kf2 = kf2_init(quat_from_euler(roll, pitch, psi), p.kf2, fc_tilt ? p.fc_sigma_tilt_rad : p.init_sigma_tilt_rad,
                     p.init_sigma_heading_rad);
    s.has_kf2 = true;
    s.ref_heading_sens = 0.0;
}

// synthetic_ahrs._reacquire_heading: after a gap left the heading unknown, take it from the
// magnetometer levelled with our roll/pitch; keep roll/pitch and their sigma
inline void ahrs_reacquire_heading(Ahrs& s, const V3& mag_body, double t, const AhrsParams& p) {
    Kf2& k = s.kf2;
    const V3& Bn = p.field_nav_gauss;
    V3 e;
    M3 cov;
    kf2_euler_and_cov(k, e, cov);
    const double nB = norm3(Bn);
    const V3 m{mag_body[0] - k.mag_bias[0] * nB, mag_body[1] - k.mag_bias[1] * nB, mag_body[2] - k.mag_bias[2] * nB};
    const V3 m_lev = m3v(dcm_from_euler(e[0], e[1], 0.0), m);
    if (!(std::hypot(m_lev[0], m_lev[1]) > 0.05 * nB)) return;  // no usable horizontal field: wait
    const double psi = std::atan2(Bn[1], Bn[0]) - std::atan2(m_lev[1], m_lev[0]);
    const Q4 q = quat_from_euler(e[0], e[1], psi);
    const double sigma_tilt = std::sqrt(std::max(cov[0], cov[4]));
    const Kf2 fresh = kf2_init(q, p.kf2, sigma_tilt, p.init_sigma_heading_rad);
    P9 P = k.P;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < KN; ++j) { P[i * KN + j] = 0.0; P[j * KN + i] = 0.0; }
    set_block3(P, 0, 0, block3(fresh.P, 0, 0));
    k.q_nav_from_body = fresh.q_nav_from_body;
    k.P = P;
    k.n_resets += 1;
    if (k.has_S)  // the attitude anew (its heading sigma covers it)
        for (int i = 0; i < 3 * NC; ++i) k.S[i] = 0.0;
    s.reacquire_heading = false;
    s.ref_heading_sens = 0.0;
    s.last_mag_update_s = t;
}

inline void ahrs_on_imu(Ahrs& s, const V3& g_s, bool has_mag, const V3& mag_s, double t, const AhrsParams& p) {
    if (!finite3(g_s)) return;  // a dropped/NaN sample is skipped
    const V3 gyro_b = m3v(p.C_body_from_sensor, g_s);
    if (s.has_time && t <= s.time_s) return;
    const V3 bias = s.has_kf2 ? s.kf2.gyro_bias_rad_s : V3{0.0, 0.0, 0.0};
    const V3 w{gyro_b[0] - bias[0], gyro_b[1] - bias[1], gyro_b[2] - bias[2]};
    V3 wlp;
    Q4 qf;
    if (!s.has_omega_lp || !s.has_time || !s.has_q_free) {
        wlp = w;
        qf = {1.0, 0.0, 0.0, 0.0};
    } else {
        const double dt = t - s.time_s;
        const double k = dt / (p.rate_lp_tau_s + dt);
        for (int i = 0; i < 3; ++i) wlp[i] = s.omega_lp_rad_s[i] + k * (w[i] - s.omega_lp_rad_s[i]);
        qf = s.q_gyro_free;
        if (dt <= p.kf2.max_dt_s) {
            s.imu_integrated_s += dt;
            qf = quat_unit(quat_mul(qf, quat_from_rotvec({w[0] * dt, w[1] * dt, w[2] * dt})));  // rectangular
            if (s.has_gyro_prev) {
                // each step's error is (mean rate - sample) dt; E|w_k - w_k-1|^2 = 6 sigma_w^2 over 3 axes
                const double d0 = w[0] - s.gyro_prev_rad_s[0], d1 = w[1] - s.gyro_prev_rad_s[1],
                             d2 = w[2] - s.gyro_prev_rad_s[2];
                const double sigma_w2 = (d0 * d0 + d1 * d1 + d2 * d2) / 6.0;
                s.gyro_free_var_rad2 = s.gyro_free_var_rad2 + sigma_w2 * dt * dt;
            }
        } else {
            s.imu_not_integrated_s += dt;
            if (!s.health.anchors->empty())
                clear_anchors(s.health);  // a gap the gyro-only attitude did not see: re-lay the anchors
        }
    }
    s.has_q_free = true; s.q_gyro_free = qf;
    s.has_omega_lp = true; s.omega_lp_rad_s = wlp;
    s.has_time = true; s.time_s = t;
    s.has_gyro_prev = true; s.gyro_prev_rad_s = w;
    ahrs_trust(s, t, p);
    if (!s.has_kf2) {
        if (!s.has_first_imu) { s.has_first_imu = true; s.first_imu_time_s = t; }
        ahrs_init_without_reference(s, has_mag, mag_s, t, p);
        return;
    }
    double dt2;
    const Kf2Diag d2 = kf2_predict(s.kf2, gyro_b, t, p.kf2, dt2);
    if (d2.code == Kf2Code::gap && kf2_heading_var(s.kf2) > std::pow(p.init_sigma_heading_rad, 2))
        s.reacquire_heading = true;
    if (s.trusted && (s.snaps->empty() || t - s.snaps->back().t >= p.bias_snapshot_period_s)) {
        auto keep = std::make_shared<std::vector<Snapshot>>();
        keep->reserve(s.snaps->size() + 1);
        for (const Snapshot& sn : *s.snaps)
            if (t - sn.t <= 3.0 * p.bias_revert_age_s) keep->push_back(sn);
        keep->push_back(Snapshot{t, s.kf2.gyro_bias_rad_s, s.kf2.mag_bias, s.kf2.q_nav_from_body, s.q_gyro_free, s.kf2.P});
        s.snaps = std::move(keep);
    }
    if (!has_mag || !finite3(mag_s)) return;
    const V3 mag_b = m3v(p.C_body_from_sensor, mag_s);
    const V3& Bn = p.field_nav_gauss;
    const bool kf1_learning = s.trusted && s.has_fc_last && p.use_fc_yaw;
    if (kf1_learning && (!s.kf1_learn.has_time || t - s.kf1_learn.time_s >= p.kf1.min_update_interval_s - 1e-6)) {
        const M3 C_fc = dcm_from_euler(s.fc_last_e[0], s.fc_last_e[1], s.fc_last_e[2]);
        const Kf1Code c = kf1_step(s.kf1_learn, mag_b, C_fc, Bn, wlp, t, p.kf1);
        s.n_kf1_rejected += (c == Kf1Code::chi2_gate || c == Kf1Code::rate_gate) ? 1 : 0;
    }
    s.kf1_learning = kf1_learning;
    if (t - s.last_mag_update_s >= p.mag_update_interval_s - 1e-6) {
        V3 m = mag_b;
        if (kf1_applied_usable(s)) m = kf1_correct_mag(*s.kf1_applied, mag_b);
        if (s.reacquire_heading) {
            ahrs_reacquire_heading(s, m, t, p);
            return;
        }
        kf2_propagate(s.kf2, p.kf2);
        double sens = s.ref_heading_sens;
        double v0 = 0.0;
        if (sens > 0.0) v0 = kf2_heading_var(s.kf2);
        const Kf2Diag d = p.mag_heading ? kf2_update_mag_heading(s.kf2, m, Bn, p.kf2) : kf2_update_mag(s.kf2, m, Bn, p.kf2);
        if (sens > 0.0 && d.fused && v0 > 0.0) sens *= std::min(1.0, kf2_heading_var(s.kf2) / v0);  // a <- (1 - k) a
        s.last_mag_update_s = t;
        s.ref_heading_sens = sens;
    }
}

// synthetic_ahrs.air_references (eq. 22, 24, 37): false + reason, or the references
struct AirRefs {
    bool ok;
    const char* why;
    double phi_ref, theta_ref, s_phi, s_theta, gain;
};

inline AirRefs air_references(const AirOut& air, double roll, double pitch, const V3& w, bool has_k, double k_alpha,
                              const AhrsParams& p) {
    if (!air.usable()) return {false, air.unusable_reason(), 0, 0, 0, 0, 0};
    if (std::fabs(roll) > p.air_roll_limit_rad) return {false, "roll beyond limit", 0, 0, 0, 0, 0};
    if (std::fabs(pitch) > p.air_pitch_limit_rad) return {false, "pitch beyond limit", 0, 0, 0, 0, 0};
    const V3 ed = euler_rates(roll, pitch, w, true);  // (roll, pitch from kf2_euler_and_cov: numpy scalars)
    if (std::max(std::fabs(ed[0]), std::fabs(ed[1])) > p.air_rate_limit_rad_s)
        return {false, "attitude rate beyond limit", 0, 0, 0, 0, 0};
    const double v = air.tas_m_s;
    const double x = v * ed[2] / G_M_S2;
    const double phi_ref = std::atan(x);  // eq. 24
    const double turn_gain = (v / G_M_S2) / (1.0 + x * x);
    const double sv = std::max(-0.99, std::min(0.99, air.alt_rate_m_s / v));
    const double gamma = std::asin(sv);
    double sig_alpha = 3.0 * (PI_ / 180.0);  // math.radians(3.0)
    double alpha = 0.0;
    if (has_k) {
        const double n = 1.0 / std::max(0.3, std::cos(roll));
        alpha = k_alpha * n / (0.5 * air.density_kg_m3 * v * v);
        sig_alpha = 0.0;
    }
    const double theta_ref = gamma + alpha * std::cos(roll);  // eq. 22 (beta = 0)
    const double sig_gamma = p.air_sigma_alt_rate_m_s / (v * std::sqrt(1.0 - sv * sv));
    const double sig_theta = std::sqrt(std::pow(p.air_sigma_pitch_rad, 2) + std::pow(sig_gamma, 2) + std::pow(sig_alpha, 2));
    return {true, "", phi_ref, theta_ref, p.air_sigma_roll_rad, sig_theta, turn_gain};
}

inline void ahrs_on_air(Ahrs& s, double press_abs_pa, bool has_diff, double diff, bool has_temp, double temp, double t,
                        const AhrsParams& p) {
    if (s.air.has_time && t <= s.air.time_s) return;
    if (!(std::isfinite(press_abs_pa) && press_abs_pa > 0.0)) {
        s.air_active = false;
        s.air_off_reason = "no valid static pressure";
        return;
    }
    has_diff = has_diff && std::isfinite(diff);
    has_temp = has_temp && std::isfinite(temp);
    s.air_last = air_data_step(s.air, press_abs_pa, has_diff, diff, has_temp, temp, t, p.air);
    s.has_air_last = true;
    if (!s.has_kf2) { s.air_active = false; s.air_off_reason = "not initialised"; return; }
    if (s.trusted) { s.air_active = false; s.air_off_reason = "reference trusted"; return; }
    if (t - s.last_air_update_s < p.air_update_interval_s - 1e-6) return;
    V3 e;
    M3 cov;
    kf2_euler_and_cov(s.kf2, e, cov);
    const V3 w = s.has_omega_lp ? s.omega_lp_rad_s : V3{0.0, 0.0, 0.0};
    const AirRefs r = air_references(s.air_last, e[0], e[1], w, s.has_k_alpha, s.k_alpha_pa, p);
    if (!r.ok) { s.air_active = false; s.air_off_reason = r.why; return; }
    const Kf2Diag d = kf2_update_air(s.kf2, r.phi_ref, r.theta_ref, r.s_phi, r.s_theta, r.gain, p.kf2);
    s.last_air_update_s = t;
    s.air_active = d.fused;
    s.air_off_reason = d.fused ? "" : "gated";
}

// synthetic_ahrs._learn_alpha: alpha_meas = (theta_fc - asin(h_dot / v)) / cos(phi); k = alpha q_dyn / n
inline void ahrs_learn_alpha(Ahrs& s, const V3& e, double dt, const AhrsParams& p) {
    if (!s.has_air_last || !s.air_last.usable() || dt <= 0.0) return;
    const double roll = e[0], pitch = e[1];
    if (std::fabs(roll) > p.air_roll_limit_rad || std::fabs(pitch) > p.air_pitch_limit_rad) return;
    const AirOut& air = s.air_last;
    const double v = air.tas_m_s;
    const double gamma = std::asin(std::max(-0.99, std::min(0.99, air.alt_rate_m_s / v)));
    const double n = 1.0 / std::cos(roll);
    const double k_meas = (pitch - gamma) / std::cos(roll) * (0.5 * air.density_kg_m3 * v * v) / n;
    if (!s.has_k_alpha) {
        s.has_k_alpha = true;
        s.k_alpha_pa = k_meas;
        return;
    }
    s.k_alpha_pa = s.k_alpha_pa + dt / (p.alpha_tau_s + dt) * (k_meas - s.k_alpha_pa);
}

inline void ahrs_on_fc_attitude(Ahrs& s, const V3& e, double t, const AhrsParams& p) {
    if (!finite3(e)) return;
    const bool has_prev = s.has_fc_last;
    const double prev_t = s.fc_last_t;
    const bool imu_behind = s.has_time && t - s.time_s > p.kf2.max_dt_s;
    if (s.has_q_free && imu_behind) {
        // our gyro-only attitude is not current: no agreement test across the gap, anchors re-laid
        s.health.has_fc_time = true;
        s.health.fc_time_s = t;
        clear_anchors(s.health);
    } else if (s.has_q_free) {
        Q4 q_g = s.q_gyro_free;
        if (s.has_gyro_prev && s.has_time && t != s.time_s) {  // our gyro-only attitude at the FC's time
            const double lead = t - s.time_s;
            q_g = quat_mul(q_g, quat_from_rotvec(V3{s.gyro_prev_rad_s[0] * lead, s.gyro_prev_rad_s[1] * lead,
                                                    s.gyro_prev_rad_s[2] * lead}));
        }
        health_on_attitude(s.health, dcm_from_euler(e[0], e[1], e[2]), dcm_from_quat(q_g), t, p.health,
                           s.gyro_free_var_rad2);
    }
    s.has_fc_last = true;
    s.fc_last_t = t;
    s.fc_last_e = e;
    ahrs_trust(s, s.has_time ? std::max(t, s.time_s) : t, p);
    if (!s.trusted) return;
    ahrs_learn_alpha(s, e, has_prev ? t - prev_t : 0.0, p);
    if (!s.has_kf2) {
        if (!s.has_time || !p.use_fc_yaw) return;  // (no FC yaw: started from the magnetometer)
        s.kf2 = kf2_init(quat_from_euler(e[0], e[1], e[2]), p.kf2, p.fc_sigma_tilt_rad, p.fc_sigma_yaw_rad);
        s.has_kf2 = true;
        s.last_ref_update_s = t;
        s.ref_heading_sens = 1.0;
        return;
    }
    if (t - s.last_ref_update_s < p.ref_update_interval_s - 1e-6 || imu_behind) return;
    kf2_propagate(s.kf2, p.kf2);
    const double v0 = kf2_heading_var(s.kf2);
    const Kf2Diag d = kf2_update_reference(s.kf2, e, t, p.fc_sigma_tilt_rad, p.fc_sigma_yaw_rad, p.kf2, p.use_fc_yaw);
    double sens = s.ref_heading_sens;
    s.last_ref_update_s = t;
    if (!p.use_fc_yaw) return;  // roll/pitch only: no FC yaw error inherited
    if (d.fused) s.reacquire_heading = false;  // the FC gave the heading back
    if (d.code == Kf2Code::reset_to_reference) {
        sens = 1.0;
    } else if (d.fused && v0 > 0.0) {
        const double k = std::max(0.0, 1.0 - kf2_heading_var(s.kf2) / v0);
        sens = (1.0 - k) * sens + k;  // a <- (1 - k) a + k
    }
    s.ref_heading_sens = sens;
}

// FcStatusEvent: system_status < 0 / ok flags < 0: None (unchanged)
inline void ahrs_on_fc_status(Ahrs& s, bool has_status, long status, int attitude_ok, int horiz_pos_ok, double t,
                              const AhrsParams& p) {
    if (has_status) {
        s.health.has_system_status = true;
        s.health.system_status = status;
    }
    if (attitude_ok >= 0 || horiz_pos_ok >= 0) {
        // health_on_ekf_status(h, bool(a), bool(h)): a flag never reported reads False there
        const int a = attitude_ok >= 0 ? attitude_ok : s.health.attitude_ok;
        const int h = horiz_pos_ok >= 0 ? horiz_pos_ok : s.health.horiz_pos_ok;
        s.health.attitude_ok = a == 1 ? 1 : 0;
        s.health.horiz_pos_ok = h == 1 ? 1 : 0;
    }
    ahrs_trust(s, s.has_time ? s.time_s : t, p);
}

inline void ahrs_unseen(Ahrs& s, double unseen_s, const AhrsParams& p) {
    if (!(std::isfinite(unseen_s) && unseen_s >= 0.0))
        throw std::invalid_argument("unseen_s must be finite and >= 0, got " + py_repr(unseen_s));
    if (!s.has_kf2) return;
    kf2_unseen(s.kf2, unseen_s, p.kf2);
    s.kf2.has_time = false;
    s.kf2.has_omega_prev = false;
    s.kf2.has_cov_time = false;
    s.kf2.has_acc_angle = false;
    s.kf2.acc_omega_sq = 0.0;
    s.kf1_learn.has_time = false;
    s.has_time = false;
    s.has_fc_last = false;
    s.air = AirState();
    s.has_air_last = false;
    s.last_mag_update_s = s.last_air_update_s = s.last_ref_update_s = -INFINITY;
    s.health.has_fc_time = false;
    clear_anchors(s.health);
    s.health.has_check_time = false;
    s.health.has_good_since = false;
    s.health.attitude_ok = s.health.horiz_pos_ok = -1;  // the rebooted FC's estimator has not spoken yet
    s.health.has_first_attitude = false;
    s.snaps = std::make_shared<const std::vector<Snapshot>>();
    s.reacquire_heading = kf2_heading_var(s.kf2) > std::pow(p.init_sigma_heading_rad, 2);
}

// synthetic_ahrs_takeoff: the residual magnetometer biases learnt at rest (a body-fixed bias and the
// launcher's or site's field look alike there) go back to 0 with their prior, their cross-covariances
// and consider sensitivities zeroed; the bias snapshots (learnt on the ground) are dropped.
inline void ahrs_takeoff(Ahrs& s, const AhrsParams& p) {
    if (!s.has_kf2) return;
    for (int i = 6; i < 9; ++i)
        for (int j = 0; j < KN; ++j) s.kf2.P[i * KN + j] = s.kf2.P[j * KN + i] = 0.0;
    for (int i = 6; i < 9; ++i) s.kf2.P[i * KN + i] = std::pow(p.kf2.sigma_mag_bias_init, 2);
    if (s.kf2.has_S)
        for (int i = 6; i < 9; ++i)
            for (int j = 0; j < NC; ++j) s.kf2.S[i * NC + j] = 0.0;
    s.kf2.mag_bias = V3{0, 0, 0};
    s.snaps = std::make_shared<const std::vector<Snapshot>>();
}

struct AhrsOut {  // SyntheticAhrsOutput's numbers (the strings and flags from the state)
    bool valid;
    double roll, pitch, heading, roll_sigma, pitch_sigma, heading_sigma;
};

inline AhrsOut ahrs_output(const Ahrs& s, const AhrsParams& p) {
    if (!s.has_kf2) return {false, NAN, NAN, NAN, NAN, NAN, NAN};
    V3 e;
    M3 cov;
    kf2_euler_and_cov(s.kf2, e, cov);
    // the filter's heading variance plus the FC yaw error it inherited and the magnetometer's
    // consider parameters' share [T S_gamma P_c S_gamma^T T^T]_33 (synthetic_ahrs module docstring)
    double var_h = cov[8] + std::pow(s.ref_heading_sens * p.fc_sigma_yaw_rad, 2);
    if (p.consider_mag_errors && s.kf2.has_S) {
        const M3 T = euler_rate_matrix_reported(e[0], e[1]);
        std::array<double, NC> h{};  // row 3 of T S_gamma
        for (int j = 0; j < NC; ++j)
            h[j] = (T[6] * s.kf2.S[0 * NC + j] + T[7] * s.kf2.S[1 * NC + j]) + T[8] * s.kf2.S[2 * NC + j];
        Mat<NC, NC> Pc{};
        if (kf1_applied_usable(s)) {
            for (int i = 0; i < 9; ++i)
                for (int j = 0; j < 9; ++j) Pc[i * NC + j] = s.kf1_applied->P[(3 + i) * K1 + 3 + j];
        } else {
            for (int i = 0; i < 9; ++i) {
                const double sg = i < 3 ? p.kf1_sigma_scale_init : p.kf1_sigma_cross_init;
                Pc[i * NC + i] = sg * sg;
            }
        }
        Pc[NC * NC - 1] = std::pow(p.field_model_sigma_rad, 2);
        double v = 0.0;
        for (int i = 0; i < NC; ++i) {
            double r = 0.0;
            for (int j = 0; j < NC; ++j) r += Pc[i * NC + j] * h[j];
            v += h[i] * r;
        }
        var_h += v;
    }
    return {true, e[0], e[1], e[2], std::sqrt(cov[0]), std::sqrt(cov[4]), std::sqrt(var_h)};
}

}  // namespace azimuthd
