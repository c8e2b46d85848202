// Method C's filter step with its magnetometer chain as one core call: what service/pipeline.py
// Pipeline._filter_chain_python does (it stays the reference; tests/test_core_filter_chain.py proves
// the Pipeline's outputs equal), on the states the Pipeline holds in the core:
//   attitude filter step (core/polar_attitude.hpp) -> rest detection and the zero-rate update
//   (core/zero_rate.hpp) -> the heading filter's tilt (the trusted, fresh FC's, else C's own) ->
//   the hard iron removed, the field checked against the undisturbed one (core/mag_disturbance.hpp)
//   -> the magnetometer usability (core/mag_usability.hpp) -> method D's correction once it covers
//   enough attitudes (core/mag_deviation.hpp) -> the heading filter step (core/polar_heading.hpp)
//   -> its zero-rate update.
// The events come out as (kind, text) with the reference's words and figures (printf's %.Nf rounds
// as Python's format does); the heading filter's own event stays with the Pipeline.
#pragma once

#include <cstdio>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "mag_deviation.hpp"
#include "mag_disturbance.hpp"
#include "mag_usability.hpp"
#include "polar_attitude.hpp"
#include "polar_heading.hpp"
#include "zero_rate.hpp"

namespace azimuthd {

// service/pipeline.py Pipeline._mag_hard_iron_residual on the held MagDisturbance (its P read here,
// no array built): with C = C_P_from_body and the levelled field m = C m_body, H^2 = m_x^2 + m_y^2,
// g = [m_y, -m_x, 0] / H^2, the heading-equivalent sigma s_eq = sqrt(H^2 g^T C P C^T g) (evaluated
// left to right, as numpy does), and with it the uncompensated soft iron: hypot(s_eq, soft_iron
// |m_body|). Not given (false) without a P or a horizontal field.
inline bool mag_hard_iron_residual(const MagDisturbance& md, const Q4& q, const V3& mb, double soft_iron,
                                   double& out) {
    if (!md.has_P) return false;
    const M3 C = dcm_from_quat(q);
    double m[3];
    for (int i = 0; i < 3; ++i) m[i] = C[3 * i] * mb[0] + C[3 * i + 1] * mb[1] + C[3 * i + 2] * mb[2];
    const double H2 = std::pow(m[0], 2.0) + std::pow(m[1], 2.0);
    if (H2 <= 0.0) return false;
    const double g[3] = {m[1] / H2, -m[0] / H2, 0.0 / H2};
    double u[3], v[3], w[3];
    for (int j = 0; j < 3; ++j) u[j] = g[0] * C[j] + g[1] * C[3 + j] + g[2] * C[6 + j];             // g C
    for (int j = 0; j < 3; ++j) v[j] = u[0] * md.P[j] + u[1] * md.P[3 + j] + u[2] * md.P[6 + j];   // (g C) P
    for (int j = 0; j < 3; ++j) w[j] = v[0] * C[3 * j] + v[1] * C[3 * j + 1] + v[2] * C[3 * j + 2];  // ... C^T
    const double x = w[0] * g[0] + w[1] * g[1] + w[2] * g[2];
    const double arg = H2 * x;
    if (arg < 0.0) throw std::domain_error("math domain error");  // math.sqrt's (a ValueError in Python)
    const double s_eq = std::sqrt(arg);
    const double n = std::sqrt(mb[0] * mb[0] + mb[1] * mb[1] + mb[2] * mb[2]);
    out = std::hypot(s_eq, soft_iron * n);
    return true;
}

namespace filter_chain {

// the held states and their converted params (the Pipeline's)
struct States {
    polar::State* att;
    const polar::Params* att_p;
    zero_rate::State* zr;
    const zero_rate::Params* zr_p;
    MagDisturbance* md;
    const MagDisturbanceParams* md_p;
    MagUsability* mu;
    const MagUsabilityParams* mu_p;
    polar_heading::State* hdg;
    const polar_heading::Params* hdg_p;
    Deviation* dev;              // nullptr: no deviation state
};

// one filter step's inputs (body axes: the filter-rate mean rate and specific force, the newest
// magnetometer) and what the chain reads of the Pipeline
struct Inputs {
    double t;
    V3 gyro_b, accel_b;
    bool has_mag;
    V3 mag_b;
    M3 C_body_from_sensor;
    // _heading_tilt: the FC's attitude, present and trusted by method B (its age is tested here)
    bool fc_trusted;
    double fc_time_s, fc_roll, fc_pitch, fc_sigma_tilt_rad, fc_tilt_max_age_s;
    // the heading filter's magnetometer inputs
    double declination, declination_sigma;
    bool has_field_model;
    V3 field_model;
    // method D: applied at all (deviation_apply), its coverage threshold and bins
    bool dev_apply;
    double dev_min_coverage;
    int dev_min_samples_per_bin;
};

// the Pipeline's flags the chain reads and sets
struct Flags {
    bool dev_hard_iron_changed;
    int dev_in_use;  // -1 None, 0 False, 1 True
};

struct Output {
    polar::Diag adiag;
    bool has_att = false;          // the attitude estimate after the step (C levelled)
    bool has_mag_s = false;        // the magnetometer for B (sensor axes): usable, undisturbed, hard iron removed
    V3 mag_s{};
    bool mag_raw = false;          // mag_b_raw is not None (D learns on the measured field)
    bool has_tilt = false;         // the heading filter stepped
    polar_heading::Diag hdiag;
    bool has_rest = false;
    zero_rate::RestRate rest;
    bool has_mag_status = false;   // Pipeline.mag_status changed this step
    std::string mag_status;
    std::vector<std::pair<const char*, std::string>> events;
};

inline std::string f1(const char* fmt, double a) {
    char b[200];
    std::snprintf(b, sizeof b, fmt, a);
    return b;
}

constexpr const char* COASTS = "): the heading coasts on the gyros, its sigma growing";

inline void step(const States& S, const Inputs& in, Flags& fl, Output& out) {
    const double t = in.t;
    // C's attitude filter
    out.adiag = polar::step(*S.att, t, in.gyro_b, in.accel_b, *S.att_p);
    if (out.adiag.code == polar::UPDATE && out.adiag.why == polar::RELEVELLED)
        out.events.emplace_back("attitude", f1("re-levelled at rest: tilt corrected by %.1f deg from the accelerometer",
                                               rad2deg(out.adiag.relevel_rad)) +
                                                f1(" after %.1f s of gated-out updates", S.att_p->relevel_rest_s));
    // zero-rate updates only while the vehicle may be at rest (as the re-levelling)
    if (S.att_p->relevel_allowed) {
        out.has_rest = zero_rate::rest_step(*S.zr, t, in.gyro_b, in.accel_b, *S.zr_p, out.rest);
    } else if (S.zr->has_time) {
        *S.zr = zero_rate::State{};
    }
    double ratio;
    if (out.has_rest) zero_rate::attitude_update(*S.att, out.rest, *S.zr_p, ratio);
    const polar::State& att = *S.att;
    out.has_att = att.initialised;
    double a_roll = 0.0, a_pitch = 0.0;
    Mat<2, 2> a_cov{};
    if (out.has_att) polar::estimate(att, a_roll, a_pitch, a_cov);

    // _heading_tilt: (roll, pitch, 2x2 covariance); the FC's plus its turn over its age, (|w_xy| age)^2
    bool has_tilt = false, fc_tilt = false;
    double roll = 0.0, pitch = 0.0;
    Mat<2, 2> cov{};
    const double fc_age = t - in.fc_time_s;
    if (in.fc_trusted && 0.0 <= fc_age && fc_age <= in.fc_tilt_max_age_s) {
        const double wn = std::sqrt(in.gyro_b[0] * in.gyro_b[0] + in.gyro_b[1] * in.gyro_b[1]);
        const double var = in.fc_sigma_tilt_rad * in.fc_sigma_tilt_rad + (wn * fc_age) * (wn * fc_age);
        has_tilt = fc_tilt = true;
        roll = in.fc_roll;
        pitch = in.fc_pitch;
        cov = {var, 0.0, 0.0, var};
    } else if (out.has_att) {
        has_tilt = true;
        roll = a_roll;
        pitch = a_pitch;
        cov = a_cov;
    }

    // _mag_disturbance: the field less the learnt hard iron, None while disturbed (the raw field
    // before C has levelled)
    bool has_hi = false;
    V3 mag_hi{};
    if (in.has_mag && !out.has_att) {
        has_hi = true;
        mag_hi = in.mag_b;
    } else if (in.has_mag) {
        if (!(finite3(in.mag_b) && std::isfinite(t)))
            throw std::invalid_argument("mag_body_gauss (3), q_P_from_body (4) and time_s must be finite");
        if (S.md->has_time && t - S.md->time_s < 0.0)
            throw std::invalid_argument("time_s must not decrease");
        const MagDisturbanceOut v = S.md->step(t, in.mag_b, att.q_P_from_body, *S.md_p);
        if (v.relearned) {
            out.events.emplace_back("magnetic_disturbance", "hard iron changed (a magnet attached?): re-learning it, "
                                                            "the heading coasts on the gyros meanwhile");
            fl.dev_hard_iron_changed = S.dev != nullptr;
        }
        if (v.changed) {
            if (v.usable) {
                std::string txt = "undisturbed: used again, hard iron [";
                for (int i = 0; i < 3; ++i) txt += (i ? ", " : "") + f1("%+.3f", v.hard_iron_gauss[i]);
                out.events.emplace_back("magnetic_disturbance",
                                        txt + f1("] G +- %.3f G", v.hard_iron_sigma_gauss));
            } else {
                out.events.emplace_back("magnetic_disturbance", "rejected (" + v.reason + COASTS);
            }
        }
        has_hi = v.usable;
        mag_hi = v.mag_corrected_gauss;
    }

    // _mag_usable: the usability verdict on the raw field levelled with the tilt
    MagVerdictOut v;
    bool have_v;
    const double w[3] = {in.gyro_b[0], in.gyro_b[1], in.gyro_b[2]};
    if (!in.has_mag) {
        have_v = S.mu->stale(t, true, true, w, *S.mu_p, v);
    } else {
        // a NEW hard iron learnt (a magnet attached) is removed before the model tests
        const bool use_hi = S.md->n_relearns > 0 && !S.md->relearning;
        const bool tilt_ok = has_tilt && std::isfinite(roll) && std::isfinite(pitch);
        const double m3[3] = {in.mag_b[0], in.mag_b[1], in.mag_b[2]};
        const double hi[3] = {S.md->hard_iron_gauss[0], S.md->hard_iron_gauss[1], S.md->hard_iron_gauss[2]};
        const double nan3[3] = {NAN, NAN, NAN};
        v = S.mu->step(t, m3, tilt_ok, tilt_ok ? roll : NAN, tilt_ok ? pitch : NAN, true, true, w, use_hi,
                       use_hi ? hi : nan3, *S.mu_p);
        have_v = true;
    }
    if (have_v) {
        const bool pending = S.mu->usable < 0;
        out.has_mag_status = true;
        out.mag_status = v.usable ? "usable" : (pending ? v.reason : "rejected: " + v.reason);
        if (v.usable && !S.md->reason.empty() && S.md->has_P) out.mag_status = "rejected: " + S.md->reason;
        if (v.changed) out.events.emplace_back("magnetometer", v.usable ? std::string("usable")
                                                                        : "rejected (" + v.reason + COASTS);
    }
    const bool usable = in.has_mag && S.mu->usable == 1;
    bool has_mag = usable && has_hi;
    V3 mag_b = mag_hi;
    out.has_mag_s = out.mag_raw = has_mag;
    if (has_mag) {
        const M3& C = in.C_body_from_sensor;   // C^T m
        for (int i = 0; i < 3; ++i) out.mag_s[i] = C[i] * mag_hi[0] + C[3 + i] * mag_hi[1] + C[6 + i] * mag_hi[2];
    }

    // _deviation_corrected: D's correction of the MEASURED field once it covers enough attitudes
    bool corrected = false;
    if (has_mag && S.dev != nullptr && in.dev_apply) {
        const Deviation& d = *S.dev;
        const int k = in.dev_min_samples_per_bin;
        const double hf = Deviation::fraction(d.heading_counts, k), rf = Deviation::fraction(d.roll_counts, k),
                     pf = Deviation::fraction(d.pitch_counts, k);
        const double overall = std::min(hf, std::min(rf, pf));
        const bool use = overall >= in.dev_min_coverage && !fl.dev_hard_iron_changed;
        if ((use ? 1 : 0) != fl.dev_in_use) {
            fl.dev_in_use = use ? 1 : 0;
            std::string txt = std::string("compensation ") + (use ? "applied" : "not applied") + ": ";
            if (fl.dev_hard_iron_changed)
                txt += "the hard iron was re-learnt (a magnet attached?) since its calibration";
            else
                txt += f1("coverage %.2f", overall) + f1(" (headings %.2f", hf) + f1(", rolls %.2f", rf) +
                       f1(", pitches %.2f)", pf) + f1(", needed %.2f", in.dev_min_coverage);
            out.events.emplace_back("deviation", txt);
        }
        if (use && S.hdg->initialised && out.has_att) {
            double heading, hvar;
            polar_heading::estimate(*S.hdg, heading, hvar);
            if (std::isfinite(heading)) {
                double model[3];
                d.model(heading, a_roll, a_pitch, model);
                for (int i = 0; i < 3; ++i) mag_b[i] = in.mag_b[i] - model[i];
                corrected = true;
            }
        }
    }

    out.has_tilt = has_tilt;
    if (!has_tilt) return;
    polar_heading::Inputs u{};
    u.time_s = t;
    u.gyro = in.gyro_b;
    u.roll = roll;
    u.pitch = pitch;
    u.cov_rp = cov;
    u.has_mag = has_mag;
    if (has_mag) {
        u.mag = mag_b;
        u.declination = in.declination;
        u.declination_sigma = in.declination_sigma;
        u.has_field_model = in.has_field_model;
        u.field_model = in.has_field_model ? in.field_model : V3{0.0, 0.0, 0.0};
        if (corrected) {  // D applied: its residual, max over the axes
            double r[3];
            S.dev->residual_sigma(r);
            u.has_residual = true;
            u.residual_sigma = std::max(r[0], std::max(r[1], r[2]));
        } else {          // else C's uncalibrated model with the learnt hard iron's uncertainty
            u.has_residual = out.has_att && mag_hard_iron_residual(*S.md, att.q_P_from_body, mag_b,
                                                                  S.hdg_p->uncalibrated_soft_iron, u.residual_sigma);
        }
    } else {
        u.declination = u.declination_sigma = NAN;
        u.has_residual = false;
        u.residual_sigma = 0.0;
        u.has_field_model = false;
        u.field_model = {0.0, 0.0, 0.0};
    }
    // the platform formulation: C's full attitude, its attitude-error covariance, levelled with the FC's tilt
    u.has_q = out.has_att;
    if (u.has_q) {
        u.q_P = att.q_P_from_body;
        u.has_cov_att = true;
        u.cov_att = polar::att_block(att.P);
        u.level_with_roll_pitch = fc_tilt;
    }
    out.hdiag = polar_heading::step(*S.hdg, u, *S.hdg_p);
    if (out.hdiag.code == polar_heading::BAD_DECLINATION)
        throw std::invalid_argument("declination_rad must be finite when a magnetometer sample is given");
    if (out.has_rest) zero_rate::heading_update(*S.hdg, out.rest, *S.zr_p, ratio);
}

}  // namespace filter_chain
}  // namespace azimuthd
