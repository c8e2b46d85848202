// The Pipeline's per-IMU-sample hot path (issue 19 items 1, 3): the QUIET samples of a batch, in
// C++. service/pipeline.py Pipeline.on_imu stays the reference and handles every other sample;
// Pipeline.on_imu_batch hands the rows here and gets back the first sample that needs Python.
//
// A quiet sample is one that on_imu would take through these steps only, none of them deciding
// anything: the input checks pass with no event (core/input_checks.hpp; their verdict on the
// sample that stops the loop is handed back, the check having run once), the sample is finite and
// its FC time increases, the Pipeline's strapdown integrates it (core/strapdown.hpp; a gap is not
// quiet), method A's in-flight step propagates it and may store its magnetometer sample with
// neither a solve nor an accepted solver submit due (core/azimuth_propagation.hpp), the filter-rate
// accumulators take it with no filter step due, and the output attitude is turned by it
// (estimators/output_propagation.py output_step, twin below). Whether the Pipeline is in a state
// where such samples exist at all (phase in flight, nothing pending, A not in its boost window...)
// is judged in Python before each run: those conditions change only on a sample Python handles.
//
// Every step is first done on copies; only a sample found quiet is committed, so the one that
// stops the loop leaves the state as it was before it (bar its input check, whose verdict goes
// back). The reference's operation order throughout; the build has no FMA contraction.
//
// On the ground (phase pre-launch) ground_run below takes the quiet samples instead: the phases
// (core/phases.hpp) stepped with no event, method A's delay line and method E's rest data
// (core/ground.hpp), the accumulators and the output attitude.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "azimuth_output.hpp"
#include "azimuth_propagation.hpp"
#include "ground.hpp"
#include "input_checks.hpp"
#include "phases.hpp"
#include "strapdown.hpp"

namespace azimuthd {

// estimators/output_propagation.py OutputState
struct OutputProp {
    bool has = false;            // an OutputState exists (None in the reference otherwise)
    double q[4] = {1, 0, 0, 0};  // q_nav_from_body, Hamilton [w, x, y, z]
    double time_s = 0.0;
    bool has_inc = false;        // increment_prev is not None
    double inc[3] = {0, 0, 0};
};

// output_step: the attitude turned by one sample's increment plus the coning term; false when the
// interval is not integrable (the reference returns None: the state is then gone).
inline bool output_step(OutputProp& o, double time_s, const double g[3], const double b[3], double max_dt_s) {
    const double dt = time_s - o.time_s;
    if (!(0.0 < dt && dt <= max_dt_s)) return false;
    const double ax = (g[0] - b[0]) * dt, ay = (g[1] - b[1]) * dt, az = (g[2] - b[2]) * dt;
    if (!(std::isfinite(ax) && std::isfinite(ay) && std::isfinite(az))) return false;
    double px = ax, py = ay, pz = az;
    if (o.has_inc) {  // + a_prev x a / 12
        const double ux = o.inc[0], uy = o.inc[1], uz = o.inc[2];
        px += (uy * az - uz * ay) / 12.0;
        py += (uz * ax - ux * az) / 12.0;
        pz += (ux * ay - uy * ax) / 12.0;
    }
    const double angle = std::sqrt(px * px + py * py + pz * pz);
    const double k = angle < 1e-6 ? 0.5 - angle * angle / 48.0 : std::sin(0.5 * angle) / angle;
    const double rw = std::cos(0.5 * angle), rx = k * px, ry = k * py, rz = k * pz;
    const double qw = o.q[0], qx = o.q[1], qy = o.q[2], qz = o.q[3];
    const double nw = qw * rw - qx * rx - qy * ry - qz * rz;
    const double nx = qw * rx + qx * rw + qy * rz - qz * ry;
    const double ny = qw * ry - qx * rz + qy * rw + qz * rx;
    const double nz = qw * rz + qx * ry - qy * rx + qz * rw;
    const double n = std::sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
    o.q[0] = nw / n; o.q[1] = nx / n; o.q[2] = ny / n; o.q[3] = nz / n;
    o.time_s = time_s;
    o.has_inc = true;
    o.inc[0] = ax; o.inc[1] = ay; o.inc[2] = az;
    return true;
}

// The Pipeline's per-sample fields (service/pipeline.py: the attributes of the same names are
// properties over this object when the core runs; over the reference's SampleState otherwise).
struct SampleState {
    bool has_last_time = false;     // last_time_fc_s (None when false)
    double last_time_fc_s = 0.0;
    bool has_last_rx = false;       // _last_rx_s
    double last_rx_s = 0.0;
    double filter_due_s = -std::numeric_limits<double>::infinity();
    double acc_gyro[3] = {0, 0, 0};
    double acc_accel[3] = {0, 0, 0};
    long long acc_n = 0;
    bool has_acc_mag = false;       // _acc_mag (None when false)
    double acc_mag[3] = {0, 0, 0};
    OutputProp out;                 // _out
    double out_bias_body[3] = {0, 0, 0};  // _out_bias_body_rad_s
    bool has_out_sample = false;    // _out_rx_s / _out_gyro_s: the sample _out was last turned to
    double out_rx_s = 0.0;
    double out_gyro[3] = {0, 0, 0};
};

// The filter accumulators take one sample (Pipeline.on_imu's per-sample tail, SampleState.accumulate):
// true when no filter step is due at time t.
inline bool accumulate(SampleState& h, const double g[3], const double a[3], const double* m, double t,
                       double filter_period_s) {
    for (int k = 0; k < 3; ++k) h.acc_gyro[k] = h.acc_gyro[k] + g[k];
    for (int k = 0; k < 3; ++k) h.acc_accel[k] = h.acc_accel[k] + a[k];
    h.acc_n += 1;
    if (m != nullptr) {
        h.has_acc_mag = true;
        for (int k = 0; k < 3; ++k) h.acc_mag[k] = m[k];
    }
    return t < h.filter_due_s - 0.05 * filter_period_s;
}

// The output attitude turned by one sample (SampleState.turn_output): gb the body-axes rate.
inline void turn_output(SampleState& h, double t, const double gb[3], double max_dt_s, double rx, const double g[3]) {
    if (!h.out.has) return;
    if (!output_step(h.out, t, gb, h.out_bias_body, max_dt_s)) h.out.has = false;
    h.has_out_sample = true;
    h.out_rx_s = rx;
    for (int k = 0; k < 3; ++k) h.out_gyro[k] = g[k];
}

// Method A in flight (estimators/azimuth.py azimuth_step with the core's azimuth_propagate), the
// per-sample part: taken from the AzimuthState for one run and handed back as a new one.
struct AzimuthRun {
    bool active = false;            // A steps these samples (phase "flight", not in its boost window)
    StrapdownState sd{};            // AzimuthState.strapdown
    double G[36] = {};              // G_gyro (3 x 12)
    double C[9] = {};               // C_isf_sf
    double bias[3] = {0, 0, 0};     // gyro_bias_rad_s (A's own, from its levelling)
    double max_dt_s = 0.1;          // params.strapdown.max_dt_s
    double launch_time_s = 0.0;
    double mag_skip_after_launch_s = 0.0, mag_decimation_s = 0.0;
    long long max_fit_samples = 0;
    long long n_samples = 0;        // len(samples)
    double last_mag_s = -std::numeric_limits<double>::infinity();
    double last_solve_s = -std::numeric_limits<double>::infinity();
    double solve_period_s = 0.0;    // azimuth_step's inline period (the Pipeline's: infinite)
    double next_solve_s = 0.0;      // the Pipeline's solver schedule
    bool submit_phase = false;      // phase == "flight"
    bool submit_blocked = false;    // the solver is busy: a submit due is refused (the reference's submit returns
                                    // False and changes nothing), so the sample stays quiet; set by Python per run
    // the magnetometer samples stored in this run: time, h (3), C_sf_from_isf (3 x 3), G (3 x 12)
    std::vector<double> rec;
    static constexpr int REC = 1 + 3 + 9 + 36;
    AzimuthOutputCfg out;           // what A's output needs beside G and C (set when first read)
};

// Method A's step of one sample (azimuth_step with neither a solve nor a submit due), on copies:
// false when it is not quiet (not integrated, or a solve or a solver submit due on it). `store`:
// its magnetometer sample `m` (nullptr: none) goes into the fit.
inline bool azimuth_try(const AzimuthRun& a, double t, const double* g, const double* m, StrapdownState& a_sd,
                        double aG[36], double aC[9], bool& store) {
    a_sd = a.sd;
    for (int k = 0; k < 36; ++k) aG[k] = a.G[k];
    for (int k = 0; k < 9; ++k) aC[k] = a.C[k];
    const double w[3] = {g[0] - a.bias[0], g[1] - a.bias[1], g[2] - a.bias[2]};
    double dt = 0.0;
    if (azimuth_propagate(a_sd, aG, aC, w, t, a.max_dt_s, dt) != StrapdownCode::integrated) return false;
    store = m != nullptr && t - a.launch_time_s >= a.mag_skip_after_launch_s &&
            t - a.last_mag_s >= a.mag_decimation_s - 1e-9 && a.n_samples < a.max_fit_samples;
    const long long n_after = a.n_samples + (store ? 1 : 0);
    if (t - a.last_solve_s >= a.solve_period_s && n_after > 0) return false;  // azimuth_step would solve
    if (t >= a.next_solve_s && a.submit_phase && n_after > 0 && !a.submit_blocked) return false;  // a submit due
    return true;
}

// ... and committed (the sample found quiet): the stored record is time, h, C_sf_from_isf = C^T, G.
inline void azimuth_commit(AzimuthRun& a, double t, const double* m, const StrapdownState& a_sd, const double aG[36],
                           const double aC[9], bool store) {
    a.sd = a_sd;
    for (int k = 0; k < 36; ++k) a.G[k] = aG[k];
    for (int k = 0; k < 9; ++k) a.C[k] = aC[k];
    if (store) {
        a.rec.push_back(t);
        for (int k = 0; k < 3; ++k) a.rec.push_back(m[k]);
        for (int rr = 0; rr < 3; ++rr)
            for (int cc = 0; cc < 3; ++cc) a.rec.push_back(aC[3 * cc + rr]);  // C_isf_sf^T
        for (int k = 0; k < 36; ++k) a.rec.push_back(aG[k]);
        a.n_samples += 1;
        a.last_mag_s = t;
    }
}

// What on_imu_batch passes that Python owns and only Python changes.
struct HotInputs {
    double gyro_bias[3];            // Pipeline.gyro_bias_rad_s
    double C_bs[9];                 // C_body_from_sensor, row-major
    double strapdown_max_dt_s;
    double out_max_dt_s;            // polar_att_params.max_dt_s
    double filter_period_s;
    bool int16_source;
};

enum HotStop : int { HS_END = 0, HS_CHECK = 1, HS_PIPELINE = 2 };

// One row of a run: its input check (verdict back to the caller) and the Pipeline's own (finite,
// time increasing); false: the run stops at this row. hot_run and ground_run share it.
inline bool row_accepted(const SampleState& h, InputChecks& ic, const HotInputs& in, const double* r, int& verdict,
                         bool& checked) {
    const double t = r[0];
    const double* g = r + 2;
    const double* acc = r + 5;
    const double v[6] = {g[0], g[1], g[2], acc[0], acc[1], acc[2]};
    verdict = ic.step(v, t, in.int16_source);
    checked = true;
    if (verdict != IC_OK) return false;
    if (!(std::isfinite(t) && std::isfinite(g[0]) && std::isfinite(g[1]) && std::isfinite(g[2]) &&
          std::isfinite(acc[0]) && std::isfinite(acc[1]) && std::isfinite(acc[2])))
        return false;
    return !(h.has_last_time && t <= h.last_time_fc_s);
}

// A quiet sample's times, committed first (on_imu's order).
inline void commit_times(SampleState& h, double t, double rx, long& handled) {
    h.last_time_fc_s = t;
    h.has_last_time = true;
    ++handled;
    h.last_rx_s = rx;
    h.has_last_rx = true;
}

// A quiet sample's last steps (on_imu's order): the filters' accumulators, then the output attitude
// turned by the body-frame rate.
inline void accumulate_and_turn(SampleState& h, const HotInputs& in, const double* g, const double* acc,
                                const double* m, double t, double rx) {
    accumulate(h, g, acc, m, t, in.filter_period_s);
    if (h.out.has) {
        const double* C = in.C_bs;
        const double gb[3] = {C[0] * g[0] + C[1] * g[1] + C[2] * g[2], C[3] * g[0] + C[4] * g[1] + C[5] * g[2],
                              C[6] * g[0] + C[7] * g[1] + C[8] * g[2]};
        turn_output(h, t, gb, in.out_max_dt_s, rx, g);
    }
}

// Rows: IMU_RECORD as float64 (time_fc, time_rx, gyro 3, accel 3, mag 3 (NaN: none), ...), `stride`
// doubles apart. From row `start`: every quiet sample committed; returns the first row not handled
// (n: all). `checked`: that row's input check ran, with the verdict `verdict`. `handled`: quiet rows.
inline long hot_run(SampleState& h, InputChecks& ic, StrapdownState* sd, AzimuthRun& a, const HotInputs& in,
                    const double* rows, long n, long stride, long start, int& verdict, bool& checked,
                    long& handled) {
    checked = false;
    verdict = 0;
    handled = 0;
    const double due_tol = 0.05 * in.filter_period_s;
    for (long i = start; i < n; ++i) {
        const double* r = rows + i * stride;
        const double t = r[0], rx = r[1];
        const double* g = r + 2;
        const double* acc = r + 5;
        const double* m = r + 8;
        if (!row_accepted(h, ic, in, r, verdict, checked)) return i;
        const bool has_mag = std::isfinite(m[0]) && std::isfinite(m[1]) && std::isfinite(m[2]);
        // method A's step, on copies
        StrapdownState a_sd{};
        double aG[36], aC[9];
        bool store = false;
        if (a.active && !azimuth_try(a, t, g, has_mag ? m : nullptr, a_sd, aG, aC, store)) return i;
        // the Pipeline's strapdown, on a copy
        StrapdownState p_sd{};
        if (sd != nullptr) {
            p_sd = *sd;
            const double w[3] = {g[0] - in.gyro_bias[0], g[1] - in.gyro_bias[1], g[2] - in.gyro_bias[2]};
            double dt = 0.0;
            const StrapdownCode code = strapdown_step(p_sd, w, t, in.strapdown_max_dt_s, dt);
            if (code != StrapdownCode::integrated && code != StrapdownCode::first_sample) return i;
        }
        if (!(t < h.filter_due_s - due_tol)) return i;  // a filter step
        // quiet: commit, in on_imu's order
        commit_times(h, t, rx, handled);
        if (a.active) azimuth_commit(a, t, m, a_sd, aG, aC, store);
        if (sd != nullptr) *sd = p_sd;
        accumulate_and_turn(h, in, g, acc, has_mag ? m : nullptr, t, rx);
    }
    checked = false;
    verdict = 0;
    return n;
}

// The ground run's inputs: the Pipeline's held phases (service/phases_core.py HeldPhaseState) and its
// converted params, its GroundState (nullptr: _step_azimuth does nothing, method A being off), and
// what Pipeline._flight_evidence builds from, fixed over a batch (the FC's messages cut batches): the
// FC's armed / flying / landed (tri-states as core/phases.hpp Evidence) and the air data's time with
// the airspeed and altitude rate it would give while fresh (NaN: it gives none).
struct GroundInputs {
    phases::State* ph = nullptr;
    const phases::Params* pp = nullptr;
    GroundState* gs = nullptr;
    int armed = -1, fc_reports_flying = -1, fc_landed = -1;
    bool has_air = false;
    double air_time_s = 0.0, air_max_age_s = 1.0;
    double airspeed_m_s = NAN, alt_rate_m_s = NAN;
};

// The QUIET ground samples (phase pre-launch) of a batch, from row `start`, as hot_run's in flight: a
// quiet ground sample is one on which on_imu passes the input checks with no event, sees finite and
// increasing time, steps the phases with no event and the phase staying pre-launch (they hold the
// levelling, the take-off and started-in-flight rules: any decision of theirs words an event),
// steps _step_azimuth's pre-launch branch (ground_step: it decides nothing), accumulates for the
// filters with no filter step due and turns the output attitude. The phases step on a copy,
// committed only for a quiet sample; the one that stops the loop leaves every state as it was (bar
// its input check, whose verdict goes back).
inline long ground_run(SampleState& h, InputChecks& ic, const GroundInputs& gi, const HotInputs& in,
                       const double* rows, long n, long stride, long start, int& verdict, bool& checked,
                       long& handled) {
    checked = false;
    verdict = 0;
    handled = 0;
    const double due_tol = 0.05 * in.filter_period_s;
    phases::Evidence ev;
    ev.armed = gi.armed;
    ev.fc_reports_flying = gi.fc_reports_flying;
    ev.fc_landed = gi.fc_landed;
    phases::Events events;
    for (long i = start; i < n; ++i) {
        const double* r = rows + i * stride;
        const double t = r[0], rx = r[1];
        const double* g = r + 2;
        const double* acc = r + 5;
        const double* m = r + 8;
        if (!row_accepted(h, ic, in, r, verdict, checked)) return i;
        const bool has_mag = std::isfinite(m[0]) && std::isfinite(m[1]) && std::isfinite(m[2]);
        // Pipeline._flight_evidence at t: the air data counts while fresh
        const bool fresh = gi.has_air && std::fabs(t - gi.air_time_s) <= gi.air_max_age_s;
        ev.airspeed_m_s = fresh ? gi.airspeed_m_s : NAN;
        ev.alt_rate_m_s = fresh ? gi.alt_rate_m_s : NAN;
        // the phases, on a copy
        phases::State ph = *gi.ph;
        events.clear();
        phases::phase_step(ph, g, acc, t, *gi.pp, ev, events);
        if (!events.empty() || ph.phase != phases::PRE_LAUNCH) return i;
        if (!(t < h.filter_due_s - due_tol)) return i;  // a filter step
        // quiet: commit, in on_imu's order
        commit_times(h, t, rx, handled);
        const bool block_ended = ph.block_start_s && *ph.block_start_s == t;
        const bool block_passed = ph.block_passed_s && *ph.block_passed_s == t;
        *gi.ph = std::move(ph);
        if (gi.gs != nullptr) ground_step(*gi.gs, g, acc, has_mag ? m : nullptr, t, block_ended, block_passed);
        accumulate_and_turn(h, in, g, acc, has_mag ? m : nullptr, t, rx);
    }
    checked = false;
    verdict = 0;
    return n;
}

}  // namespace azimuthd
