// Magnetic disturbances in motion: the compiled twin of estimators/mag_disturbance.py
// (mag_disturbance_step), which stays the reference and holds the derivation: the hard iron b from
// pairs of samples the body turned between (z = m_1 - C_10 m_0 = (I - C_10) b + noise, a Kalman
// update gated by its NIS; relearnt when consecutive pairs disagree), and the field's low-passed
// norm and dip against the recent undisturbed ones. tests/test_core_mag_disturbance.py proves them
// equal (1e-9 relative: the 3x3 solve and inverse round differently from numpy's LAPACK).
#pragma once

#include <cmath>
#include <string>

#include "ahrs_math.hpp"

namespace azimuthd {

struct MagDisturbanceParams {
    double model_norm_gauss = 0.5, model_dip_rad = 0.0, model_norm_tolerance = 0.25, model_dip_tolerance_rad = 0.0;
    double mag_noise_gauss = 0.003, hard_iron_prior_sigma_gauss = 0.016, hard_iron_walk_gauss_rt_s = 1e-5;
    double soft_iron_fraction = 0.01, turn_error_fraction = 0.005, pair_min_angle_rad = 0.0,
           pair_max_interval_s = 2.0, pair_gate_chi2 = 16.27;
    int relearn_after_pairs = 3;
    double relearn_sigma_gauss = 0.5, learnt_sigma_gauss = 0.05, current_tau_s = 0.1, reference_tau_s = 20.0;
    double norm_tolerance = 0.10, dip_tolerance_rad = 0.0, min_undisturbed_s = 0.5, new_field_after_s = 20.0,
           new_field_min_rate_rad_s = 0.0;
};

struct MagDisturbanceOut {
    bool usable = false;
    std::string reason;
    bool changed = false;
    V3 mag_corrected_gauss{};   // valid when usable
    V3 hard_iron_gauss{};
    double hard_iron_sigma_gauss = 0.0, norm_ratio = NAN, dip_diff_rad = NAN;
    bool relearned = false;
};

// the reference's _kind: the reason up to its first ':' and then up to " ("
inline std::string reason_kind(const std::string& r) {
    std::string k = r.substr(0, r.find(':'));
    const size_t p = k.find(" (");
    return p == std::string::npos ? k : k.substr(0, p);
}

struct MagDisturbance {
    V3 hard_iron_gauss{0.0, 0.0, 0.0};
    bool has_P = false;
    M3 P{};
    bool has_time = false;
    double time_s = 0.0;
    bool has_anchor = false;
    double anchor_t = 0.0;
    V3 anchor_m{};
    Q4 anchor_q{};
    int bad_pairs = 0;
    bool relearning = false, last_pair_ok = true;
    int n_pairs = 0, n_relearns = 0;
    bool has_norm_lp = false, has_dip_lp = false, has_norm_ref = false, has_dip_ref = false;
    double norm_lp = 0.0, dip_lp = 0.0, norm_ref = 0.0, dip_ref = 0.0;
    double undisturbed_s = 0.0;
    bool disturbed = true;
    bool has_candidate = false;
    double cand[3] = {0, 0, 0};
    std::string reason = "no magnetometer sample yet";
    bool has_m_last = false;  // the last new sample: a repeat of it is not a new one
    V3 m_last{};

    static double lp(bool has_prev, double prev, double x, double dt, double tau) {
        if (!has_prev || dt <= 0.0) return x;
        return prev + (x - prev) * std::min(1.0, dt / tau);
    }

    // m, q finite, t not before the last sample (the caller checked)
    MagDisturbanceOut step(double t, const V3& m, const Q4& q, const MagDisturbanceParams& p) {
        if (has_m_last && m[0] == m_last[0] && m[1] == m_last[1] && m[2] == m_last[2]) {
            // a held repeat: nothing new; the last fresh sample's verdict
            MagDisturbanceOut out;
            out.usable = reason.empty();
            out.reason = reason;
            out.changed = false;
            out.mag_corrected_gauss = {m[0] - hard_iron_gauss[0], m[1] - hard_iron_gauss[1], m[2] - hard_iron_gauss[2]};
            out.hard_iron_gauss = hard_iron_gauss;
            const double dmax = std::max(std::max(P[0], P[4]), P[8]);
            out.hard_iron_sigma_gauss = std::sqrt(std::max(dmax, 0.0));
            if (!relearning && has_norm_ref) {
                out.norm_ratio = norm_lp / norm_ref;
                out.dip_diff_rad = dip_lp - dip_ref;
            }
            return out;
        }
        const double dt = has_time ? t - time_s : 0.0;
        M3 Pk = has_P ? P : M3{};
        if (!has_P) {  // np.eye(3) * prior^2
            const double s2 = p.hard_iron_prior_sigma_gauss * p.hard_iron_prior_sigma_gauss;
            Pk = {s2, 0.0, 0.0, 0.0, s2, 0.0, 0.0, 0.0, s2};
        }
        V3 b = hard_iron_gauss;
        const M3 C_PB = dcm_from_quat(q);
        bool relearned = false;

        // 1. the hard iron, from pairs of samples the body turned between
        const double walk = p.hard_iron_walk_gauss_rt_s * p.hard_iron_walk_gauss_rt_s * dt;
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) Pk[3 * i + j] = Pk[3 * i + j] + (i == j ? walk : 0.0);
        int bad = bad_pairs, npairs = n_pairs, nrel = n_relearns;
        bool relearn = relearning, last_ok = last_pair_ok;
        double turn_rate = 0.0;
        bool new_anchor = false;
        if (!has_anchor) {
            new_anchor = true;
        } else {
            const M3 C_10 = mm<3, 3, 3>(tr<3, 3>(C_PB), dcm_from_quat(anchor_q));
            const double trace = C_10[0] + C_10[4] + C_10[8];
            const double angle = std::acos(std::max(-1.0, std::min(1.0, (trace - 1.0) / 2.0)));
            if (t > anchor_t) turn_rate = angle / (t - anchor_t);
            if (angle >= p.pair_min_angle_rad) {
                M3 Hm{};
                const M3 I = eye<3>();
                for (int k = 0; k < 9; ++k) Hm[k] = I[k] - C_10[k];
                const V3 Cm = mv<3, 3>(C_10, anchor_m);
                const V3 z{m[0] - Cm[0], m[1] - Cm[1], m[2] - Cm[2]};
                const double mmag = norm3(m);
                const double r = 2.0 * (p.mag_noise_gauss * p.mag_noise_gauss) +
                                 2.0 * ((p.soft_iron_fraction * mmag) * (p.soft_iron_fraction * mmag)) +
                                 (p.turn_error_fraction * angle * mmag) * (p.turn_error_fraction * angle * mmag);
                const V3 Hb = mv<3, 3>(Hm, b);
                const V3 nu{z[0] - Hb[0], z[1] - Hb[1], z[2] - Hb[2]};
                auto innov_cov = [&](const M3& PP) {
                    M3 S = mm<3, 3, 3>(mm<3, 3, 3>(Hm, PP), tr<3, 3>(Hm));
                    for (int i = 0; i < 3; ++i) S[4 * i] = S[4 * i] + r;
                    return S;
                };
                M3 S = innov_cov(Pk);
                const V3 Sn = solve<3>(S, nu);
                const double nis = nu[0] * Sn[0] + nu[1] * Sn[1] + nu[2] * Sn[2];
                npairs += 1;
                last_ok = nis <= p.pair_gate_chi2;
                bad = last_ok ? 0 : bad + 1;
                if (bad >= p.relearn_after_pairs) {  // the hard iron changed (a magnet attached)
                    const double s2 = p.relearn_sigma_gauss * p.relearn_sigma_gauss;
                    Pk = {s2, 0.0, 0.0, 0.0, s2, 0.0, 0.0, 0.0, s2};
                    bad = 0;
                    relearn = true;
                    relearned = true;
                    nrel += 1;
                    S = innov_cov(Pk);
                    last_ok = false;
                }
                if (last_ok || relearn) {
                    const M3 K = mm<3, 3, 3>(mm<3, 3, 3>(Pk, tr<3, 3>(Hm)), inv<3>(S));
                    const V3 Knu = mv<3, 3>(K, nu);
                    for (int i = 0; i < 3; ++i) b[i] = b[i] + Knu[i];
                    M3 I_KH = mm<3, 3, 3>(K, Hm);
                    for (int k = 0; k < 9; ++k) I_KH[k] = I[k] - I_KH[k];
                    M3 Pn = mm<3, 3, 3>(mm<3, 3, 3>(I_KH, Pk), tr<3, 3>(I_KH));
                    const M3 KK = mm<3, 3, 3>(K, tr<3, 3>(K));
                    for (int k = 0; k < 9; ++k) Pn[k] = Pn[k] + KK[k] * r;
                    for (int i = 0; i < 3; ++i)
                        for (int j = 0; j < 3; ++j) Pk[3 * i + j] = 0.5 * (Pn[3 * i + j] + Pn[3 * j + i]);
                }
                new_anchor = true;
            } else if (t - anchor_t > p.pair_max_interval_s) {
                new_anchor = true;
            }
        }
        const double dmax = std::max(std::max(Pk[0], Pk[4]), Pk[8]);
        const double sigma_b = std::sqrt(std::max(dmax, 0.0));
        if (relearn && sigma_b < p.learnt_sigma_gauss && last_ok) relearn = false;

        // 2. the field against the recent undisturbed one (and the model)
        const V3 mc{m[0] - b[0], m[1] - b[1], m[2] - b[2]};
        const double nrm = norm3(mc);
        const V3 mp = mv<3, 3>(C_PB, mc);
        const double dip = std::atan2(mp[2], std::hypot(mp[0], mp[1]));
        const double nlp = lp(has_norm_lp, norm_lp, nrm, dt, p.current_tau_s);
        const double dlp = lp(has_dip_lp, dip_lp, dip, dt, p.current_tau_s);
        const bool model_ok = std::fabs(nlp / p.model_norm_gauss - 1.0) <= p.model_norm_tolerance &&
                              std::fabs(dlp - p.model_dip_rad) <= p.model_dip_tolerance_rad;
        bool has_ref = has_norm_ref;
        double nref = norm_ref, dref = dip_ref;
        bool has_cand = has_candidate;
        double c0 = cand[0], c1 = cand[1], c2 = cand[2];
        double undist = undisturbed_s;
        bool dist = disturbed;
        double ratio = NAN, ddip = NAN;
        if (relearn) {
            undist = 0.0;
            dist = true;
        } else if (!has_ref) {
            if (model_ok) {  // the first reference: samples that agree with the model
                has_ref = true;
                nref = nlp;
                dref = dlp;
                dist = false;
                undist = p.min_undisturbed_s;
            }
        } else {
            ratio = nlp / nref;
            ddip = dlp - dref;
            const bool inside = std::fabs(ratio - 1.0) <= p.norm_tolerance && std::fabs(ddip) <= p.dip_tolerance_rad;
            if (inside) {
                undist += dt;
                if (undist >= p.min_undisturbed_s) {
                    dist = false;
                    const double k = std::min(1.0, dt / p.reference_tau_s);
                    nref += (nlp - nref) * k;
                    dref += (dlp - dref) * k;
                }
                has_cand = false;
            } else {
                undist = 0.0;
                dist = true;
                if (has_cand && std::fabs(nlp / c0 - 1.0) <= p.norm_tolerance &&
                    std::fabs(dlp - c1) <= p.dip_tolerance_rad) {
                    const double k = std::min(1.0, dt / p.reference_tau_s);
                    c0 = c0 + (nlp - c0) * k;
                    c1 = c1 + (dlp - c1) * k;
                    c2 = c2 + (turn_rate >= p.new_field_min_rate_rad_s ? dt : 0.0);
                    if (c2 >= p.new_field_after_s && model_ok) {
                        nref = c0;
                        dref = c1;
                        has_cand = false;
                        dist = false;
                        undist = p.min_undisturbed_s;
                    }
                } else {
                    has_cand = true;
                    c0 = nlp;
                    c1 = dlp;
                    c2 = 0.0;
                }
            }
        }
        char buf[400];
        std::string why;
        const double r2d = 180.0 / M_PI;
        if (relearn) {
            std::snprintf(buf, sizeof buf, "re-learning its hard iron (a magnet attached?): sigma %.3f G > %.3f G or "
                          "its pairs still inconsistent", sigma_b, p.learnt_sigma_gauss);
            why = buf;
        } else if (!has_ref) {
            std::snprintf(buf, sizeof buf, "magnetic disturbance: field %.3f G, dip %.1f deg not the model's "
                          "(%.3f G, %.1f deg)", nlp, dlp * r2d, p.model_norm_gauss, p.model_dip_rad * r2d);
            why = buf;
        } else if (dist) {
            std::snprintf(buf, sizeof buf, "magnetic disturbance: field %.3f G, dip %.1f deg vs the recent undisturbed "
                          "%.3f G, %.1f deg (tolerance %.0f %%, %.0f deg)", nlp, dlp * r2d, nref, dref * r2d,
                          100 * p.norm_tolerance, p.dip_tolerance_rad * r2d);
            why = buf;
        }
        MagDisturbanceOut out;
        out.usable = why.empty();
        out.changed = out.usable != reason.empty() || reason_kind(why) != reason_kind(reason);
        out.reason = why;
        out.mag_corrected_gauss = mc;
        out.hard_iron_gauss = b;
        out.hard_iron_sigma_gauss = sigma_b;
        out.norm_ratio = ratio;
        out.dip_diff_rad = ddip;
        out.relearned = relearned;
        // the new state
        hard_iron_gauss = b;
        has_P = true;
        P = Pk;
        has_time = true;
        time_s = t;
        if (new_anchor) {
            has_anchor = true;
            anchor_t = t;
            anchor_m = m;
            anchor_q = q;
        }
        bad_pairs = bad;
        relearning = relearn;
        last_pair_ok = last_ok;
        n_pairs = npairs;
        n_relearns = nrel;
        has_norm_lp = has_dip_lp = true;
        norm_lp = nlp;
        dip_lp = dlp;
        has_norm_ref = has_dip_ref = has_ref;
        norm_ref = nref;
        dip_ref = dref;
        undisturbed_s = undist;
        disturbed = dist;
        has_candidate = has_cand;
        cand[0] = c0;
        cand[1] = c1;
        cand[2] = c2;
        reason = why;
        has_m_last = true;
        m_last = m;
        return out;
    }
};

}  // namespace azimuthd
