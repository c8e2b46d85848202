// estimators._core.SyntheticAhrs: method B (b2) held in the core between events. The Python face
// (estimators/core.py) keeps the reference's signatures: it converts the reference's params once
// (AhrsParams), and the reference's SyntheticAhrsState to and from this object (get_state /
// set_state: plain dicts of the reference's field names) only when asked (a copy, a test).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "synthetic_ahrs.hpp"
#include "bindings_arrays.hpp"

namespace py = pybind11;
using namespace azimuthd;

namespace {

double f(const py::handle& o, const char* name) { return o.attr(name).cast<double>(); }

V3 v3(const py::handle& o) {
    auto a = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(o);
    if (!a || a.size() != 3) throw std::invalid_argument("expected 3 values");
    return {a.data()[0], a.data()[1], a.data()[2]};
}
using azimuthd::bind::arr;
using azimuthd::bind::np1;
template <int R>
py::array_t<double> np2(const Mat<R, R>& x) {
    py::array_t<double> a({static_cast<py::ssize_t>(R), static_cast<py::ssize_t>(R)});
    for (int i = 0; i < R * R; ++i) a.mutable_data()[i] = x[i];
    return a;
}
using azimuthd::bind::opt;
py::object opt_tri(int v) { return v < 0 ? py::object(py::none()) : py::object(py::bool_(v == 1)); }
int tri(const py::handle& o) { return o.is_none() ? -1 : (o.cast<bool>() ? 1 : 0); }
bool get_opt(const py::dict& d, const char* k, double& out) {
    py::object o = d[k];
    if (o.is_none()) return false;
    out = o.cast<double>();
    return true;
}

AhrsParams params_from(const py::object& p) {
    AhrsParams c{};
    c.mag_heading = p.attr("mag_mode").cast<std::string>() == "heading";
    c.C_body_from_sensor = arr<9>(p.attr("C_body_from_sensor"));
    c.field_nav_gauss = v3(p.attr("field_nav_gauss"));
    c.fc_sigma_tilt_rad = f(p, "fc_sigma_tilt_rad");
    c.fc_sigma_yaw_rad = f(p, "fc_sigma_yaw_rad");
    c.use_fc_yaw = p.attr("use_fc_yaw").cast<bool>();
    c.ref_update_interval_s = f(p, "ref_update_interval_s");
    c.mag_update_interval_s = f(p, "mag_update_interval_s");
    c.air_update_interval_s = f(p, "air_update_interval_s");
    c.air_roll_limit_rad = f(p, "air_roll_limit_rad");
    c.air_pitch_limit_rad = f(p, "air_pitch_limit_rad");
    c.air_rate_limit_rad_s = f(p, "air_rate_limit_rad_s");
    c.air_sigma_roll_rad = f(p, "air_sigma_roll_rad");
    c.air_sigma_pitch_rad = f(p, "air_sigma_pitch_rad");
    c.air_sigma_alt_rate_m_s = f(p, "air_sigma_alt_rate_m_s");
    c.alpha_tau_s = f(p, "alpha_tau_s");
    c.rate_lp_tau_s = f(p, "rate_lp_tau_s");
    c.bias_revert_age_s = f(p, "bias_revert_age_s");
    c.bias_snapshot_period_s = f(p, "bias_snapshot_period_s");
    c.init_without_reference_s = f(p, "init_without_reference_s");
    c.init_sigma_tilt_rad = f(p, "init_sigma_tilt_rad");
    c.init_sigma_heading_rad = f(p, "init_sigma_heading_rad");
    c.field_model_sigma_rad = f(p, "field_model_sigma_rad");
    c.consider_mag_errors = p.attr("consider_mag_errors").cast<bool>();
    const py::object a = p.attr("air");
    c.air = {f(a, "alt_rate_tau_s"), a.attr("use_measured_temperature").cast<bool>(), f(a, "min_airspeed_m_s"),
             f(a, "blocked_change_pa"), f(a, "blocked_time_s"), f(a, "noise_tau_s"), f(a, "max_noise_std_m_s"),
             f(a, "max_dt_s")};
    const py::object k1 = p.attr("kf1");
    c.kf1_sigma_scale_init = f(k1, "sigma_scale_init");
    c.kf1_sigma_cross_init = f(k1, "sigma_cross_init");
    c.kf1 = {f(k1, "sigma_rw_per_sqrt_s"), f(k1, "sigma_meas"), f(k1, "chi2_gate"), f(k1, "max_rate_rad_s"),
             f(k1, "min_update_interval_s")};
    const py::object k = p.attr("kf2");
    c.kf2 = {f(k, "gyro_noise_rad_s_rthz"), f(k, "gyro_scale_sigma"), f(k, "gyro_scale_corr_s"),
             f(k, "gyro_bias_sigma_rad_s"), f(k, "gyro_bias_tau_s"), f(k, "mag_bias_sigma"), f(k, "mag_bias_tau_s"),
             f(k, "mag_sigma"), f(k, "mag_gate_sigma"), f(k, "mag_norm_tolerance"), f(k, "max_mag_rate_rad_s"),
             f(k, "air_gate_sigma"), f(k, "ref_gate_sigma"), f(k, "ref_reset_rad"), f(k, "cov_period_s"),
             f(k, "max_dt_s"), f(k, "unseen_tilt_rate_sigma_rad_s"), f(k, "unseen_tilt_max_sigma_rad"),
             f(k, "unseen_heading_rate_sigma_rad_s"), f(k, "unseen_heading_max_sigma_rad"),
             f(k, "sigma_att_init_rad"), f(k, "sigma_heading_init_rad"), f(k, "sigma_gyro_bias_init_rad_s"),
             f(k, "sigma_mag_bias_init")};
    const py::object h = p.attr("health");
    c.health = {h.attr("require_horiz_pos_ok").cast<bool>(), f(h, "max_attitude_age_s"), f(h, "anchor_period_s"),
                f(h, "window_s"), f(h, "sigma_fc_tilt_rad"), f(h, "sigma_fc_yaw_rad"), f(h, "sigma_bias_rad_s"),
                f(h, "check_period_s"), f(h, "n_sigma"), f(h, "margin_rad"), f(h, "retrust_hold_s"),
                f(h, "status_wait_s")};
    return c;
}

// --- state <-> dicts of the reference's field names ------------------------------------------

py::dict kf2_dict(const Kf2& k) {
    py::dict d;
    d["q_nav_from_body"] = np1(k.q_nav_from_body);
    d["gyro_bias_rad_s"] = np1(k.gyro_bias_rad_s);
    d["mag_bias"] = np1(k.mag_bias);
    d["P"] = np2<KN>(k.P);
    d["time_s"] = opt(k.has_time, k.time_s);
    d["omega_prev_rad_s"] = k.has_omega_prev ? py::object(np1(k.omega_prev_rad_s)) : py::object(py::none());
    d["cov_time_s"] = opt(k.has_cov_time, k.cov_time_s);
    d["acc_angle_rad"] = k.has_acc_angle ? py::object(np1(k.acc_angle_rad)) : py::object(py::none());
    d["acc_omega_sq"] = k.acc_omega_sq;
    d["n_mag_fused"] = k.n_mag_fused; d["n_mag_rejected"] = k.n_mag_rejected; d["n_mag_gated"] = k.n_mag_gated;
    d["n_air_fused"] = k.n_air_fused; d["n_air_rejected"] = k.n_air_rejected; d["n_ref_fused"] = k.n_ref_fused;
    d["n_ref_rejected"] = k.n_ref_rejected; d["n_resets"] = k.n_resets;
    if (k.has_S) {
        py::array_t<double> a({static_cast<py::ssize_t>(KN), static_cast<py::ssize_t>(NC)});
        for (int i = 0; i < KN * NC; ++i) a.mutable_data()[i] = k.S[i];
        d["consider_sens"] = a;
    } else {
        d["consider_sens"] = py::none();
    }
    return d;
}

Kf2 kf2_from(const py::dict& d) {
    Kf2 k;
    k.q_nav_from_body = arr<4>(d["q_nav_from_body"]);
    k.gyro_bias_rad_s = v3(d["gyro_bias_rad_s"]);
    k.mag_bias = v3(d["mag_bias"]);
    k.P = arr<KN * KN>(d["P"]);
    k.has_time = get_opt(d, "time_s", k.time_s);
    k.has_omega_prev = !py::object(d["omega_prev_rad_s"]).is_none();
    if (k.has_omega_prev) k.omega_prev_rad_s = v3(d["omega_prev_rad_s"]);
    k.has_cov_time = get_opt(d, "cov_time_s", k.cov_time_s);
    k.has_acc_angle = !py::object(d["acc_angle_rad"]).is_none();
    if (k.has_acc_angle) k.acc_angle_rad = v3(d["acc_angle_rad"]);
    k.acc_omega_sq = d["acc_omega_sq"].cast<double>();
    k.n_mag_fused = d["n_mag_fused"].cast<long>(); k.n_mag_rejected = d["n_mag_rejected"].cast<long>();
    k.n_mag_gated = d["n_mag_gated"].cast<long>(); k.n_air_fused = d["n_air_fused"].cast<long>();
    k.n_air_rejected = d["n_air_rejected"].cast<long>(); k.n_ref_fused = d["n_ref_fused"].cast<long>();
    k.n_ref_rejected = d["n_ref_rejected"].cast<long>(); k.n_resets = d["n_resets"].cast<long>();
    k.has_S = d.contains("consider_sens") && !py::object(d["consider_sens"]).is_none();
    if (k.has_S) k.S = arr<KN * NC>(d["consider_sens"]);
    return k;
}

py::dict kf1_dict(const Kf1& k) {  // the numbers of a Kf1State (flight_count and meta stay in Python)
    py::dict d;
    d["x"] = np1(k.x);
    d["P"] = np2<K1>(k.P);
    d["field_norm_gauss"] = opt(k.has_norm, k.field_norm_gauss);
    d["time_s"] = opt(k.has_time, k.time_s);
    d["n_updates"] = k.n_updates; d["n_rejected_chi2"] = k.n_rejected_chi2; d["n_rejected_rate"] = k.n_rejected_rate;
    return d;
}

Kf1 kf1_from(const py::dict& d) {
    Kf1 k;
    k.x = arr<K1>(d["x"]);
    k.P = arr<K1 * K1>(d["P"]);
    k.has_norm = get_opt(d, "field_norm_gauss", k.field_norm_gauss);
    k.has_time = get_opt(d, "time_s", k.time_s);
    k.n_updates = d["n_updates"].cast<long>();
    k.n_rejected_chi2 = d["n_rejected_chi2"].cast<long>();
    k.n_rejected_rate = d["n_rejected_rate"].cast<long>();
    return k;
}

py::dict air_out_dict(const AirOut& a) {
    py::dict d;
    d["time_s"] = a.time_s; d["pressure_altitude_m"] = a.pressure_altitude_m; d["density_kg_m3"] = a.density_kg_m3;
    d["temperature_used_k"] = a.temperature_used_k; d["tas_m_s"] = a.tas_m_s; d["alt_rate_m_s"] = a.alt_rate_m_s;
    d["tas_noise_std_m_s"] = a.tas_noise_std_m_s; d["airspeed_low"] = a.airspeed_low;
    d["pitot_blocked"] = a.pitot_blocked; d["pitot_noisy"] = a.pitot_noisy; d["rate_valid"] = a.rate_valid;
    return d;
}

AirOut air_out_from(const py::dict& d) {
    return AirOut{d["time_s"].cast<double>(), d["pressure_altitude_m"].cast<double>(), d["density_kg_m3"].cast<double>(),
                  d["temperature_used_k"].cast<double>(), d["tas_m_s"].cast<double>(), d["alt_rate_m_s"].cast<double>(),
                  d["tas_noise_std_m_s"].cast<double>(), d["airspeed_low"].cast<bool>(), d["pitot_blocked"].cast<bool>(),
                  d["pitot_noisy"].cast<bool>(), d["rate_valid"].cast<bool>()};
}

py::dict get_state(const Ahrs& s, const AhrsParams& p) {
    py::dict d;
    py::dict air;
    air["time_s"] = opt(s.air.has_time, s.air.time_s);
    air["altitude_m"] = s.air.altitude_m; air["alt_rate_m_s"] = s.air.alt_rate_m_s; air["tas_m_s"] = s.air.tas_m_s;
    air["tas_diff_sq_mean"] = s.air.tas_diff_sq_mean;
    air["diff_ref_pa"] = opt(s.air.has_diff_ref, s.air.diff_ref_pa);
    air["diff_change_time_s"] = s.air.diff_change_time_s; air["rate_start_time_s"] = s.air.rate_start_time_s;
    d["air"] = air;
    d["air_last"] = s.has_air_last ? py::object(air_out_dict(s.air_last)) : py::object(py::none());
    const Health& h = s.health;
    py::dict hd;
    hd["system_status"] = h.has_system_status ? py::object(py::int_(h.system_status)) : py::object(py::none());
    hd["attitude_ok"] = opt_tri(h.attitude_ok);
    hd["horiz_pos_ok"] = opt_tri(h.horiz_pos_ok);
    hd["fc_time_s"] = opt(h.has_fc_time, h.fc_time_s);
    hd["first_attitude_s"] = opt(h.has_first_attitude, h.first_attitude_s);
    hd["attitude_interval_s"] = opt(h.has_interval, h.attitude_interval_s);
    py::list anchors;
    for (const Anchor& a : *h.anchors) anchors.append(py::make_tuple(a.t_a, np2<3>(a.C_fc), np2<3>(a.C_g), a.v_a));
    hd["anchors"] = py::tuple(anchors);
    hd["max_discrepancy_rad"] = h.max_discrepancy_rad;
    hd["check_time_s"] = opt(h.has_check_time, h.check_time_s);
    hd["diverged"] = h.diverged;
    hd["good_since_s"] = opt(h.has_good_since, h.good_since_s);
    hd["ever_trusted"] = h.ever_trusted; hd["latched_out"] = h.latched_out;
    hd["silent_divergence"] = h.silent_divergence;
    hd["reason"] = std::string(h.reason);
    d["health"] = hd;
    d["q_gyro_free"] = s.has_q_free ? py::object(np1(s.q_gyro_free)) : py::object(py::none());
    d["gyro_prev_rad_s"] = s.has_gyro_prev ? py::object(np1(s.gyro_prev_rad_s)) : py::object(py::none());
    d["gyro_free_var_rad2"] = s.gyro_free_var_rad2;
    d["kf2"] = s.has_kf2 ? py::object(kf2_dict(s.kf2)) : py::object(py::none());
    d["kf1_learn"] = kf1_dict(s.kf1_learn);
    d["k_alpha_pa"] = opt(s.has_k_alpha, s.k_alpha_pa);
    d["omega_lp_rad_s"] = s.has_omega_lp ? py::object(np1(s.omega_lp_rad_s)) : py::object(py::none());
    d["fc_last"] = s.has_fc_last ? py::object(py::make_tuple(s.fc_last_t, np1(s.fc_last_e))) : py::object(py::none());
    d["time_s"] = opt(s.has_time, s.time_s);
    d["last_mag_update_s"] = s.last_mag_update_s;
    d["last_air_update_s"] = s.last_air_update_s;
    d["last_ref_update_s"] = s.last_ref_update_s;
    d["trusted"] = s.trusted;
    d["trust_reason"] = trust_text(s.trust, p.health);
    py::list snaps;
    for (const Snapshot& sn : *s.snaps)
        snaps.append(py::make_tuple(sn.t, np1(sn.b_g), np1(sn.b_m), np1(sn.q), np1(sn.q_free), np2<KN>(sn.P)));
    d["bias_snapshots"] = py::tuple(snaps);
    d["air_active"] = s.air_active;
    d["air_off_reason"] = std::string(s.air_off_reason);
    d["kf1_learning"] = s.kf1_learning;
    d["n_kf1_rejected"] = s.n_kf1_rejected;
    d["first_imu_time_s"] = opt(s.has_first_imu, s.first_imu_time_s);
    d["ref_heading_sens"] = s.ref_heading_sens;
    d["reacquire_heading"] = s.reacquire_heading;
    d["imu_integrated_s"] = s.imu_integrated_s;
    d["imu_not_integrated_s"] = s.imu_not_integrated_s;
    return d;
}

Ahrs state_from(const py::dict& d) {
    Ahrs s;
    const py::dict air = d["air"];
    s.air.has_time = get_opt(air, "time_s", s.air.time_s);
    s.air.altitude_m = air["altitude_m"].cast<double>();
    s.air.alt_rate_m_s = air["alt_rate_m_s"].cast<double>();
    s.air.tas_m_s = air["tas_m_s"].cast<double>();
    s.air.tas_diff_sq_mean = air["tas_diff_sq_mean"].cast<double>();
    s.air.has_diff_ref = get_opt(air, "diff_ref_pa", s.air.diff_ref_pa);
    s.air.diff_change_time_s = air["diff_change_time_s"].cast<double>();
    s.air.rate_start_time_s = air["rate_start_time_s"].cast<double>();
    s.has_air_last = !py::object(d["air_last"]).is_none();
    if (s.has_air_last) s.air_last = air_out_from(d["air_last"]);
    const py::dict hd = d["health"];
    Health& h = s.health;
    h.has_system_status = !py::object(hd["system_status"]).is_none();
    if (h.has_system_status) h.system_status = hd["system_status"].cast<long>();
    h.attitude_ok = tri(hd["attitude_ok"]);
    h.horiz_pos_ok = tri(hd["horiz_pos_ok"]);
    h.has_fc_time = get_opt(hd, "fc_time_s", h.fc_time_s);
    h.has_first_attitude = get_opt(hd, "first_attitude_s", h.first_attitude_s);
    h.has_interval = get_opt(hd, "attitude_interval_s", h.attitude_interval_s);
    auto anchors = std::make_shared<std::vector<Anchor>>();
    for (const py::handle a : py::tuple(hd["anchors"])) {
        const py::tuple t = py::reinterpret_borrow<py::tuple>(a);
        anchors->push_back(Anchor{t[0].cast<double>(), arr<9>(t[1]), arr<9>(t[2]), t[3].cast<double>()});
    }
    h.anchors = std::move(anchors);
    h.max_discrepancy_rad = hd["max_discrepancy_rad"].cast<double>();
    h.has_check_time = get_opt(hd, "check_time_s", h.check_time_s);
    h.diverged = hd["diverged"].cast<bool>();
    h.has_good_since = get_opt(hd, "good_since_s", h.good_since_s);
    h.ever_trusted = hd["ever_trusted"].cast<bool>();
    h.latched_out = hd["latched_out"].cast<bool>();
    h.silent_divergence = hd["silent_divergence"].cast<bool>();
    h.reason = intern(hd["reason"].cast<std::string>());
    s.has_q_free = !py::object(d["q_gyro_free"]).is_none();
    if (s.has_q_free) s.q_gyro_free = arr<4>(d["q_gyro_free"]);
    s.has_gyro_prev = !py::object(d["gyro_prev_rad_s"]).is_none();
    if (s.has_gyro_prev) s.gyro_prev_rad_s = v3(d["gyro_prev_rad_s"]);
    s.gyro_free_var_rad2 = d["gyro_free_var_rad2"].cast<double>();
    s.has_kf2 = !py::object(d["kf2"]).is_none();
    if (s.has_kf2) s.kf2 = kf2_from(d["kf2"]);
    s.kf1_learn = kf1_from(d["kf1_learn"]);
    if (!py::object(d["kf1_applied"]).is_none()) s.kf1_applied = std::make_shared<const Kf1>(kf1_from(d["kf1_applied"]));
    s.has_k_alpha = get_opt(d, "k_alpha_pa", s.k_alpha_pa);
    s.has_omega_lp = !py::object(d["omega_lp_rad_s"]).is_none();
    if (s.has_omega_lp) s.omega_lp_rad_s = v3(d["omega_lp_rad_s"]);
    s.has_fc_last = !py::object(d["fc_last"]).is_none();
    if (s.has_fc_last) {
        const py::tuple t = d["fc_last"];
        s.fc_last_t = t[0].cast<double>();
        s.fc_last_e = v3(t[1]);
    }
    s.has_time = get_opt(d, "time_s", s.time_s);
    s.last_mag_update_s = d["last_mag_update_s"].cast<double>();
    s.last_air_update_s = d["last_air_update_s"].cast<double>();
    s.last_ref_update_s = d["last_ref_update_s"].cast<double>();
    s.trusted = d["trusted"].cast<bool>();
    // the reason as worded: the next trust decision words its own
    s.trust.why = s.trusted ? TrustReason::trusted : TrustReason::text;
    s.trust.text = intern(d["trust_reason"].cast<std::string>());
    auto snaps = std::make_shared<std::vector<Snapshot>>();
    for (const py::handle a : py::tuple(d["bias_snapshots"])) {
        const py::tuple t = py::reinterpret_borrow<py::tuple>(a);
        snaps->push_back(Snapshot{t[0].cast<double>(), v3(t[1]), v3(t[2]), arr<4>(t[3]), arr<4>(t[4]), arr<KN * KN>(t[5])});
    }
    s.snaps = std::move(snaps);
    s.air_active = d["air_active"].cast<bool>();
    s.air_off_reason = intern(d["air_off_reason"].cast<std::string>());
    s.kf1_learning = d["kf1_learning"].cast<bool>();
    s.n_kf1_rejected = d["n_kf1_rejected"].cast<long>();
    s.has_first_imu = get_opt(d, "first_imu_time_s", s.first_imu_time_s);
    s.ref_heading_sens = d["ref_heading_sens"].cast<double>();
    s.reacquire_heading = d["reacquire_heading"].cast<bool>();
    s.imu_integrated_s = d["imu_integrated_s"].cast<double>();
    s.imu_not_integrated_s = d["imu_not_integrated_s"].cast<double>();
    return s;
}

// SyntheticAhrsOutput's fields but kf1_applied_flights and variant (the Python face adds them)
py::tuple output_tuple(const Ahrs& s, const AhrsParams& p) {
    const AhrsOut o = ahrs_output(s, p);
    const V3 bias = s.has_kf2 ? s.kf2.gyro_bias_rad_s : V3{0.0, 0.0, 0.0};
    const Kf2& k = s.kf2;
    const bool n = s.has_kf2;
    return py::make_tuple(s.time_s, o.valid, o.roll, o.pitch, o.heading, o.roll_sigma, o.pitch_sigma, o.heading_sigma,
                          s.trusted, trust_text(s.trust, p.health), s.air_active, s.air_off_reason, s.kf1_learning,
                          np1(bias), n ? k.n_mag_fused : 0, n ? k.n_mag_rejected : 0, n ? k.n_mag_gated : 0,
                          n ? k.n_air_fused : 0, n ? k.n_air_rejected : 0, n ? k.n_ref_fused : 0, s.n_kf1_rejected,
                          s.imu_integrated_s, s.imu_not_integrated_s);
}

struct Held {
    Ahrs s;
};

// one event on a copy that replaces the state when it completes (a refused event changes nothing);
// the output after it (None before the first IMU sample or when not wanted)
template <class F>
py::object run(Held& h, const AhrsParams& p, bool want_output, F&& event) {
    Ahrs next = h.s;
    event(next);
    py::object out = py::none();
    if (want_output && next.has_time) out = output_tuple(next, p);
    h.s = std::move(next);
    return out;
}

}  // namespace

void bind_synthetic_ahrs(py::module_& m) {
    py::class_<AhrsParams>(m, "SyntheticAhrsParams")
        .def(py::init([](const py::object& p) { return params_from(p); }), py::arg("params"),
             "estimators.synthetic_ahrs.SyntheticAhrsParams (variant b2), converted once.");

    py::class_<Held>(m, "SyntheticAhrs")
        .def(py::init([](const py::dict& state) { return Held{state_from(state)}; }), py::arg("state"),
             "From a dict of SyntheticAhrsState's fields (estimators/core.py builds it).")
        .def("get_state", [](const Held& h, const AhrsParams& p) { return get_state(h.s, p); })
        .def("imu",
             [](Held& h, const AhrsParams& p, double gx, double gy, double gz, bool has_mag, double mx, double my,
                double mz, double t, bool want) {
                 return run(h, p, want, [&](Ahrs& s) { ahrs_on_imu(s, {gx, gy, gz}, has_mag, {mx, my, mz}, t, p); });
             })
        .def("air",
             [](Held& h, const AhrsParams& p, double p_abs, bool has_diff, double diff, bool has_temp, double temp,
                double t, bool want) {
                 return run(h, p, want, [&](Ahrs& s) { ahrs_on_air(s, p_abs, has_diff, diff, has_temp, temp, t, p); });
             })
        .def("fc_attitude",
             [](Held& h, const AhrsParams& p, double r, double pi, double y, double t, bool want) {
                 return run(h, p, want, [&](Ahrs& s) { ahrs_on_fc_attitude(s, {r, pi, y}, t, p); });
             })
        .def("fc_status",
             [](Held& h, const AhrsParams& p, bool has_status, long status, int att_ok, int horiz_ok, double t,
                bool want) {
                 return run(h, p, want,
                            [&](Ahrs& s) { ahrs_on_fc_status(s, has_status, status, att_ok, horiz_ok, t, p); });
             })
        .def("output", [](Held& h, const AhrsParams& p) {
            return h.s.has_time ? py::object(output_tuple(h.s, p)) : py::object(py::none());
        })
        .def("unseen",
             [](Held& h, const AhrsParams& p, double unseen_s) {
                 run(h, p, false, [&](Ahrs& s) { ahrs_unseen(s, unseen_s, p); });
             })
        .def("takeoff", [](Held& h, const AhrsParams& p) { run(h, p, false, [&](Ahrs& s) { ahrs_takeoff(s, p); }); })
        .def("air_last",
             [](const Held& h) { return h.s.has_air_last ? py::object(air_out_dict(h.s.air_last)) : py::object(py::none()); })
        .def("kf1_learn", [](const Held& h) { return kf1_dict(h.s.kf1_learn); });
}
