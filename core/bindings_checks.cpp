// The per-sample checks held in the core between samples; this file only converts.
// - estimators._core.InputChecks: the IMU input checks (core/input_checks.hpp); the Python face is
//   service/input_checks.py CoreImuInputChecks (the reference's check(sample) -> Verdict, counts);
// - estimators._core.MagUsability: the magnetometer usability (core/mag_usability.hpp); the Python
//   face is estimators/core.py mag_usability_step / mag_usability_stale (the reference's signatures);
// - estimators._core.MagDisturbance: magnetic disturbances in motion (core/mag_disturbance.hpp); the
//   Python face is estimators/core.py mag_disturbance_step.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "input_checks.hpp"
#include "mag_disturbance.hpp"
#include "mag_usability.hpp"
#include "bindings_arrays.hpp"

namespace py = pybind11;
using namespace azimuthd;

namespace {

py::tuple input_state(const InputChecks& c) {
    py::list prev, clip_prev, clip_run;
    for (int i = 0; i < 6; ++i) {
        prev.append(c.prev[i]);
        clip_prev.append(c.clip_prev[i]);
        clip_run.append(c.clip_run[i]);
    }
    return py::make_tuple(c.has_last_t, c.last_t, c.behind_n, c.has_behind_last_t, c.behind_last_t, c.restarted,
                          c.has_prev, prev, c.same_n, c.same_since_t, c.frozen, c.live, c.live_at_run,
                          c.has_clip_prev, clip_prev, c.clip_n, clip_run);
}

void set_input_state(InputChecks& c, const py::tuple& s) {
    if (s.size() != 17) throw std::invalid_argument("InputChecks state: 17 fields expected");
    c.has_last_t = s[0].cast<bool>();
    c.last_t = s[1].cast<double>();
    c.behind_n = s[2].cast<int>();
    c.has_behind_last_t = s[3].cast<bool>();
    c.behind_last_t = s[4].cast<double>();
    c.restarted = s[5].cast<bool>();
    c.has_prev = s[6].cast<bool>();
    auto prev = s[7].cast<std::vector<double>>();
    c.same_n = s[8].cast<int>();
    c.same_since_t = s[9].cast<double>();
    c.frozen = s[10].cast<bool>();
    c.live = s[11].cast<double>();
    c.live_at_run = s[12].cast<double>();
    c.has_clip_prev = s[13].cast<bool>();
    auto clip_prev = s[14].cast<std::vector<double>>();
    c.clip_n = s[15].cast<int>();
    auto clip_run = s[16].cast<std::vector<int>>();
    if (prev.size() != 6 || clip_prev.size() != 6 || clip_run.size() != 6)
        throw std::invalid_argument("InputChecks state: 6-vectors expected");
    for (int i = 0; i < 6; ++i) {
        c.prev[i] = prev[i];
        c.clip_prev[i] = clip_prev[i];
        c.clip_run[i] = clip_run[i];
    }
}

double num(const py::handle& o, const char* name) { return o.attr(name).cast<double>(); }

MagUsabilityParams mag_params(const py::handle& o) {
    MagUsabilityParams p;
    p.field_norm_gauss = num(o, "field_norm_gauss");
    p.field_dip_rad = num(o, "field_dip_rad");
    p.norm_tolerance_fraction = num(o, "norm_tolerance_fraction");
    p.dip_tolerance_rad = num(o, "dip_tolerance_rad");
    p.window_s = num(o, "window_s");
    p.frozen_s = num(o, "frozen_s");
    p.min_rate_hz = num(o, "min_rate_hz");
    p.rate_window_s = num(o, "rate_window_s");
    py::object fs = o.attr("full_scale_gauss");
    p.has_full_scale = !fs.is_none();
    p.full_scale_gauss = p.has_full_scale ? fs.cast<double>() : 0.0;
    p.min_expected_change_gauss = num(o, "min_expected_change_gauss");
    p.motion_step_rad = num(o, "motion_step_rad");
    p.motion_rate_floor_rad_s = num(o, "motion_rate_floor_rad_s");
    return p;
}

using azimuthd::bind::opt;

py::tuple floats(const std::vector<double>& v) {
    py::tuple out(v.size());
    for (size_t i = 0; i < v.size(); ++i) out[i] = py::float_(v[i]);
    return out;
}

// MagUsabilityState's fields (estimators/mag_usability.py), as a dict of the reference's types
py::dict mag_state(const MagUsability& s) {
    py::dict d;
    d["last_mag"] = s.has_last_mag ? py::object(py::make_tuple(s.last_mag[0], s.last_mag[1], s.last_mag[2]))
                                   : py::object(py::none());
    d["changed_s"] = opt(s.has_changed_s, s.changed_s);
    d["axis_changed_s"] = py::make_tuple(opt(s.has_axis_changed[0], s.axis_changed_s[0]),
                                         opt(s.has_axis_changed[1], s.axis_changed_s[1]),
                                         opt(s.has_axis_changed[2], s.axis_changed_s[2]));
    d["new_times"] = floats(s.new_times);
    py::tuple win(s.window.size());
    for (size_t i = 0; i < s.window.size(); ++i) win[i] = py::make_tuple(s.window[i].t, s.window[i].ratio, s.window[i].dip);
    d["window"] = win;
    d["first_s"] = opt(s.has_first_s, s.first_s);
    d["last_call_s"] = opt(s.has_last_call_s, s.last_call_s);
    d["expected_change_gauss"] = s.expected_change_gauss;
    d["axis_expected_change_gauss"] = py::make_tuple(s.axis_expected_change_gauss[0], s.axis_expected_change_gauss[1],
                                                     s.axis_expected_change_gauss[2]);
    d["turned_rad"] = s.turned_rad;
    d["motion_marks"] = floats(s.motion_marks);
    d["usable"] = s.usable < 0 ? py::object(py::none()) : py::object(py::bool_(s.usable == 1));
    d["reason"] = s.reason;
    return d;
}

bool get_opt(const py::handle& o, double& v) {
    if (o.is_none()) return false;
    v = o.cast<double>();
    return true;
}

MagUsability mag_from(const py::handle& st) {
    MagUsability s;
    py::object lm = st.attr("last_mag");
    if (!lm.is_none()) {
        auto v = lm.cast<std::vector<double>>();
        if (v.size() != 3) throw std::invalid_argument("last_mag: 3 values expected");
        s.has_last_mag = true;
        for (int i = 0; i < 3; ++i) s.last_mag[i] = v[i];
    }
    s.has_changed_s = get_opt(st.attr("changed_s"), s.changed_s);
    py::tuple ac = st.attr("axis_changed_s").cast<py::tuple>();
    for (int i = 0; i < 3; ++i) s.has_axis_changed[i] = get_opt(ac[i], s.axis_changed_s[i]);
    s.new_times = st.attr("new_times").cast<std::vector<double>>();
    for (const py::handle& e : st.attr("window")) {
        py::tuple w = e.cast<py::tuple>();
        s.window.push_back({w[0].cast<double>(), w[1].cast<double>(), w[2].cast<double>()});
    }
    s.has_first_s = get_opt(st.attr("first_s"), s.first_s);
    s.has_last_call_s = get_opt(st.attr("last_call_s"), s.last_call_s);
    s.expected_change_gauss = st.attr("expected_change_gauss").cast<double>();
    auto ax = st.attr("axis_expected_change_gauss").cast<std::vector<double>>();
    for (int i = 0; i < 3; ++i) s.axis_expected_change_gauss[i] = ax.at(i);
    s.turned_rad = st.attr("turned_rad").cast<double>();
    s.motion_marks = st.attr("motion_marks").cast<std::vector<double>>();
    py::object u = st.attr("usable");
    s.usable = u.is_none() ? -1 : (u.cast<bool>() ? 1 : 0);
    s.reason = st.attr("reason").cast<std::string>();
    return s;
}

MagDisturbanceParams dist_params(const py::handle& o) {
    MagDisturbanceParams p;
    p.model_norm_gauss = num(o, "model_norm_gauss");
    p.model_dip_rad = num(o, "model_dip_rad");
    p.model_norm_tolerance = num(o, "model_norm_tolerance");
    p.model_dip_tolerance_rad = num(o, "model_dip_tolerance_rad");
    p.mag_noise_gauss = num(o, "mag_noise_gauss");
    p.hard_iron_prior_sigma_gauss = num(o, "hard_iron_prior_sigma_gauss");
    p.hard_iron_walk_gauss_rt_s = num(o, "hard_iron_walk_gauss_rt_s");
    p.soft_iron_fraction = num(o, "soft_iron_fraction");
    p.turn_error_fraction = num(o, "turn_error_fraction");
    p.pair_min_angle_rad = num(o, "pair_min_angle_rad");
    p.pair_max_interval_s = num(o, "pair_max_interval_s");
    p.pair_gate_chi2 = num(o, "pair_gate_chi2");
    p.relearn_after_pairs = o.attr("relearn_after_pairs").cast<int>();
    p.relearn_sigma_gauss = num(o, "relearn_sigma_gauss");
    p.learnt_sigma_gauss = num(o, "learnt_sigma_gauss");
    p.current_tau_s = num(o, "current_tau_s");
    p.reference_tau_s = num(o, "reference_tau_s");
    p.norm_tolerance = num(o, "norm_tolerance");
    p.dip_tolerance_rad = num(o, "dip_tolerance_rad");
    p.min_undisturbed_s = num(o, "min_undisturbed_s");
    p.new_field_after_s = num(o, "new_field_after_s");
    p.new_field_min_rate_rad_s = num(o, "new_field_min_rate_rad_s");
    return p;
}

template <size_t N>
std::array<double, N> fixed(const py::handle& o, const char* name) {
    auto v = o.cast<std::vector<double>>();
    if (v.size() != N) throw std::invalid_argument(std::string(name) + ": wrong size");
    std::array<double, N> a{};
    for (size_t i = 0; i < N; ++i) a[i] = v[i];
    return a;
}

MagDisturbance dist_from(const py::handle& st) {
    MagDisturbance s;
    s.hard_iron_gauss = fixed<3>(py::module_::import("numpy").attr("ravel")(st.attr("hard_iron_gauss")), "hard_iron_gauss");
    py::object P = st.attr("P_hard_iron");
    s.has_P = !P.is_none();
    if (s.has_P) s.P = fixed<9>(py::module_::import("numpy").attr("ravel")(P), "P_hard_iron");
    s.has_time = get_opt(st.attr("time_s"), s.time_s);
    py::object a = st.attr("anchor");
    s.has_anchor = !a.is_none();
    if (s.has_anchor) {
        py::tuple t = a.cast<py::tuple>();
        s.anchor_t = t[0].cast<double>();
        s.anchor_m = fixed<3>(py::module_::import("numpy").attr("ravel")(t[1]), "anchor m");
        s.anchor_q = fixed<4>(py::module_::import("numpy").attr("ravel")(t[2]), "anchor q");
    }
    s.bad_pairs = st.attr("bad_pairs").cast<int>();
    s.relearning = st.attr("relearning").cast<bool>();
    s.last_pair_ok = st.attr("last_pair_ok").cast<bool>();
    s.n_pairs = st.attr("n_pairs").cast<int>();
    s.n_relearns = st.attr("n_relearns").cast<int>();
    s.has_norm_lp = get_opt(st.attr("norm_lp"), s.norm_lp);
    s.has_dip_lp = get_opt(st.attr("dip_lp"), s.dip_lp);
    s.has_norm_ref = get_opt(st.attr("norm_ref"), s.norm_ref);
    s.has_dip_ref = get_opt(st.attr("dip_ref"), s.dip_ref);
    s.undisturbed_s = st.attr("undisturbed_s").cast<double>();
    s.disturbed = st.attr("disturbed").cast<bool>();
    py::object c = st.attr("candidate");
    s.has_candidate = !c.is_none();
    if (s.has_candidate) {
        auto v = fixed<3>(c, "candidate");
        for (int i = 0; i < 3; ++i) s.cand[i] = v[i];
    }
    s.reason = st.attr("reason").cast<std::string>();
    py::object ml = st.attr("m_last");
    s.has_m_last = !ml.is_none();
    if (s.has_m_last) s.m_last = fixed<3>(py::module_::import("numpy").attr("ravel")(ml), "m_last");
    return s;
}

py::array_t<double> arr_out(const double* x, py::ssize_t n) {
    py::array_t<double> a(n);
    for (py::ssize_t i = 0; i < n; ++i) a.mutable_data()[i] = x[i];
    return a;
}

// MagDisturbanceState's fields (estimators/mag_disturbance.py) as a dict of the reference's types
py::dict dist_state(const MagDisturbance& s) {
    py::dict d;
    d["hard_iron_gauss"] = arr_out(s.hard_iron_gauss.data(), 3);
    d["P_hard_iron"] = s.has_P ? py::object(arr_out(s.P.data(), 9).attr("reshape")(3, 3)) : py::object(py::none());
    d["time_s"] = opt(s.has_time, s.time_s);
    d["anchor"] = s.has_anchor ? py::object(py::make_tuple(s.anchor_t, arr_out(s.anchor_m.data(), 3),
                                                           arr_out(s.anchor_q.data(), 4)))
                               : py::object(py::none());
    d["bad_pairs"] = s.bad_pairs;
    d["relearning"] = s.relearning;
    d["last_pair_ok"] = s.last_pair_ok;
    d["n_pairs"] = s.n_pairs;
    d["n_relearns"] = s.n_relearns;
    d["norm_lp"] = opt(s.has_norm_lp, s.norm_lp);
    d["dip_lp"] = opt(s.has_dip_lp, s.dip_lp);
    d["norm_ref"] = opt(s.has_norm_ref, s.norm_ref);
    d["dip_ref"] = opt(s.has_dip_ref, s.dip_ref);
    d["undisturbed_s"] = s.undisturbed_s;
    d["disturbed"] = s.disturbed;
    d["candidate"] = s.has_candidate ? py::object(py::make_tuple(s.cand[0], s.cand[1], s.cand[2]))
                                     : py::object(py::none());
    d["reason"] = s.reason;
    d["m_last"] = s.has_m_last ? py::object(arr_out(s.m_last.data(), 3)) : py::object(py::none());
    return d;
}

py::tuple verdict(const MagVerdictOut& v) {
    return py::make_tuple(v.usable, v.reason, v.new_sample, v.changed, v.norm_ratio, v.dip_rad, v.rate_hz);
}

}  // namespace

void bind_checks(py::module_& m) {
    m.attr("IC_FLAG_TIME_RESET") = static_cast<int>(IF_TIME_RESET);
    m.attr("IC_FLAG_RESET_END") = static_cast<int>(IF_RESET_END);
    m.attr("IC_FLAG_GAP") = static_cast<int>(IF_GAP);
    m.attr("IC_FLAG_FROZEN_END") = static_cast<int>(IF_FROZEN_END);
    py::class_<InputChecks>(m, "InputChecks")
        .def(py::init([](double gyro_max, double accel_max, double clip_gyro, double clip_accel, double int16_gyro,
                         double int16_accel, double frozen_s, double gap_s, double reset_jump_s, double live_fraction,
                         double live_alpha, int clip_repeats, int frozen_min_samples, int reset_after_samples) {
                 InputChecks c;
                 c.lim = {gyro_max, accel_max, clip_gyro, clip_accel, int16_gyro, int16_accel, frozen_s, gap_s,
                          reset_jump_s, live_fraction, live_alpha, clip_repeats, frozen_min_samples,
                          reset_after_samples};
                 return c;
             }),
             py::arg("gyro_max_rad_s"), py::arg("accel_max_m_s2"), py::arg("clip_gyro_rad_s"),
             py::arg("clip_accel_m_s2"), py::arg("int16_gyro_rad_s"), py::arg("int16_accel_m_s2"), py::arg("frozen_s"),
             py::arg("gap_s"), py::arg("reset_jump_s"), py::arg("frozen_live_fraction"), py::arg("live_alpha"),
             py::arg("clip_repeats"), py::arg("frozen_min_samples"), py::arg("reset_after_samples"))
        .def("step",
             [](InputChecks& c, double gx, double gy, double gz, double ax, double ay, double az, double t,
                bool int16_source) {
                 const double v[6] = {gx, gy, gz, ax, ay, az};
                 return c.step(v, t, int16_source);
             },
             "One sample (gyro rad/s, accel m/s^2, FC time s, RAW_IMU/SCALED_IMU?): the code | flags.")
        .def("detail",
             [](const InputChecks& c) {
                 const InputDetail& d = c.detail;
                 return py::make_tuple(d.last_t_s, d.max_gyro_rad_s, d.max_accel_m_s2, d.at_int16, d.clip_n,
                                       d.behind_n, d.same_n, d.same_s, d.frozen_end_n);
             },
             "The last step's figures: (last_t_s, max_gyro, max_accel, at_int16, clip_n, behind_n, same_n, "
             "same_s, frozen_end_n).")
        .def("get_state", &input_state)
        .def("set_state", &set_input_state);

    py::class_<MagUsabilityParams>(m, "MagUsabilityParams")
        .def(py::init([](const py::object& p) { return mag_params(p); }), py::arg("params"),
             "From estimators.mag_usability.MagUsabilityParams.");
    py::class_<MagUsability>(m, "MagUsability")
        .def(py::init([](const py::object& st) { return mag_from(st); }), py::arg("state"),
             "From estimators.mag_usability.MagUsabilityState.")
        .def("step",
             [](MagUsability& s, const MagUsabilityParams& p, double t, double mx, double my, double mz, bool has_tilt,
                double roll, double pitch, bool has_gyro, bool gyro_ok, double wx, double wy, double wz, bool has_hi,
                double hx, double hy, double hz) {
                 const double m3[3] = {mx, my, mz}, w[3] = {wx, wy, wz}, hi[3] = {hx, hy, hz};
                 return verdict(s.step(t, m3, has_tilt, roll, pitch, has_gyro, gyro_ok, w, has_hi, hi, p));
             },
             "mag_usability_step: (usable, reason, new_sample, changed, norm_ratio, dip_rad, rate_hz).")
        .def("stale",
             [](MagUsability& s, const MagUsabilityParams& p, double t, bool has_gyro, bool gyro_ok, double wx,
                double wy, double wz) -> py::object {
                 const double w[3] = {wx, wy, wz};
                 MagVerdictOut v;
                 if (!s.stale(t, has_gyro, gyro_ok, w, p, v)) return py::none();
                 return verdict(v);
             },
             "mag_usability_stale: the verdict tuple, or None.")
        .def_property_readonly("usable", [](const MagUsability& s) -> py::object {
            return s.usable < 0 ? py::object(py::none()) : py::object(py::bool_(s.usable == 1));
        })
        .def_readonly("reason", &MagUsability::reason)
        .def("get_state", &mag_state, "MagUsabilityState's fields as a dict.");

    py::class_<MagDisturbanceParams>(m, "MagDisturbanceParams")
        .def(py::init([](const py::object& p) { return dist_params(p); }), py::arg("params"),
             "From estimators.mag_disturbance.MagDisturbanceParams.");
    py::class_<MagDisturbance>(m, "MagDisturbance")
        .def(py::init([](const py::object& st) { return dist_from(st); }), py::arg("state"),
             "From estimators.mag_disturbance.MagDisturbanceState.")
        .def("step",
             [](MagDisturbance& s, const MagDisturbanceParams& p, double t, double mx, double my, double mz, double qw,
                double qx, double qy, double qz) {
                 const MagDisturbanceOut o = s.step(t, {mx, my, mz}, {qw, qx, qy, qz}, p);
                 return py::make_tuple(o.usable, o.reason, o.changed,
                                       o.usable ? py::object(arr_out(o.mag_corrected_gauss.data(), 3))
                                                : py::object(py::none()),
                                       arr_out(o.hard_iron_gauss.data(), 3), o.hard_iron_sigma_gauss, o.norm_ratio,
                                       o.dip_diff_rad, o.relearned);
             },
             "mag_disturbance_step: MagDisturbanceVerdict's fields as a tuple.")
        .def_property_readonly("hard_iron_gauss", [](const MagDisturbance& s) { return arr_out(s.hard_iron_gauss.data(), 3); })
        .def_property_readonly("P_hard_iron", [](const MagDisturbance& s) -> py::object {
            return s.has_P ? py::object(arr_out(s.P.data(), 9).attr("reshape")(3, 3)) : py::object(py::none());
        })
        .def_readonly("n_relearns", &MagDisturbance::n_relearns)
        .def_readonly("relearning", &MagDisturbance::relearning)
        .def_readonly("reason", &MagDisturbance::reason)
        .def_property_readonly("time_s", [](const MagDisturbance& s) { return opt(s.has_time, s.time_s); })
        .def("get_state", &dist_state, "MagDisturbanceState's fields as a dict.");
}
