// estimators._core.PolarAttitude: method C's attitude filter (core/polar_attitude.hpp) held in the
// core between filter steps. The Python face (estimators/core.py) keeps the reference's signatures
// (estimators/polar_attitude.py): it checks the arguments as the reference does, converts the
// reference's params once (PolarAttitudeParams), words the diagnostics, and converts the
// reference's PolarAttitudeState to and from this object (get_state / set_state: dicts of the
// reference's field names) only when asked (a copy, a test, the zero-rate update at rest).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <stdexcept>
#include <string>

#include "polar_attitude.hpp"
#include "bindings_arrays.hpp"

namespace py = pybind11;
using namespace azimuthd;
using namespace azimuthd::polar;
using ArrayC = py::array_t<double, py::array::c_style | py::array::forcecast>;

namespace {

double num(const py::handle& o, const char* name) { return o.attr(name).cast<double>(); }

Params params_from(const py::object& o) {
    Params p{};
    p.update_period_s = num(o, "update_period_s");
    p.init_period_s = num(o, "init_period_s");
    p.gyro_noise_rad_s_rt_hz = num(o, "gyro_noise_rad_s_rt_hz");
    p.gyro_bias_init_sigma_rad_s = num(o, "gyro_bias_init_sigma_rad_s");
    p.gyro_bias_sigma_rad_s = num(o, "gyro_bias_sigma_rad_s");
    p.gyro_bias_tau_s = num(o, "gyro_bias_tau_s");
    p.gyro_bias_rate_sigma_rad_s2 = num(o, "gyro_bias_rate_sigma_rad_s2");
    p.gyro_bias_rate_tau_s = num(o, "gyro_bias_rate_tau_s");
    p.takeoff_bias_step_sigma_rad_s = num(o, "takeoff_bias_step_sigma_rad_s");
    p.accel_noise_m_s2 = num(o, "accel_noise_m_s2");
    p.accel_meas_floor_m_s2 = num(o, "accel_meas_floor_m_s2");
    p.vehicle_accel_sigma_m_s2 = num(o, "vehicle_accel_sigma_m_s2");
    p.vehicle_accel_tau_s = num(o, "vehicle_accel_tau_s");
    p.manoeuvre_speed_m_s = num(o, "manoeuvre_speed_m_s");
    p.earth_rate_sigma_rad_s = num(o, "earth_rate_sigma_rad_s");
    p.earth_rate_tau_s = num(o, "earth_rate_tau_s");
    p.transport_rate_sigma_rad_s = num(o, "transport_rate_sigma_rad_s");
    p.transport_rate_tau_s = num(o, "transport_rate_tau_s");
    p.accel_bias_sigma_m_s2 = num(o, "accel_bias_sigma_m_s2");
    p.accel_bias_tau_s = num(o, "accel_bias_tau_s");
    p.gyro_scale_sigma = num(o, "gyro_scale_sigma");
    p.gyro_scale_tau_s = num(o, "gyro_scale_tau_s");
    p.gravity_variation_sigma_m_s2 = num(o, "gravity_variation_sigma_m_s2");
    p.gravity_variation_tau_s = num(o, "gravity_variation_tau_s");
    p.gravity_m_s2 = num(o, "gravity_m_s2");
    p.init_tilt_sigma_rad = num(o, "init_tilt_sigma_rad");
    p.init_yaw_sigma_rad = num(o, "init_yaw_sigma_rad");
    p.max_platform_yaw_sigma_rad = num(o, "max_platform_yaw_sigma_rad");
    p.gate_chi2 = num(o, "gate_chi2");
    p.reentry_settle_chi2 = num(o, "reentry_settle_chi2");
    p.reentry_max_wait_updates = o.attr("reentry_max_wait_updates").cast<long>();
    p.reentry_match_gain = num(o, "reentry_match_gain");
    p.max_dt_s = num(o, "max_dt_s");
    p.unseen_rate_sigma_rad_s = num(o, "unseen_rate_sigma_rad_s");
    p.relevel_rest_s = num(o, "relevel_rest_s");
    p.relevel_max_rate_rad_s = num(o, "relevel_max_rate_rad_s");
    p.relevel_allowed = o.attr("relevel_allowed").cast<bool>();
    p.relevel_norm_tol_m_s2 = num(o, "relevel_norm_tol_m_s2");
    p.sample_span_max_s = num(o, "sample_span_max_s");
    p.gap_rate_walk_rad_s2_rt_hz = num(o, "gap_rate_walk_rad_s2_rt_hz");
    p.unseen_max_sigma_rad = num(o, "unseen_max_sigma_rad");
    return p;
}

using azimuthd::bind::arr;
using azimuthd::bind::np1;

py::array_t<double> np2(const double* x, py::ssize_t r, py::ssize_t c) {
    py::array_t<double> a({r, c});
    double* o = a.mutable_data();
    for (py::ssize_t i = 0; i < r * c; ++i) o[i] = x[i];
    return a;
}

using azimuthd::bind::opt;
template <size_t N>
py::object opt_arr(bool has, const std::array<double, N>& v) {
    return has ? py::object(np1(v)) : py::object(py::none());
}
bool get_opt(const py::dict& d, const char* k, double& out) {
    py::object o = d[k];
    if (o.is_none()) return false;
    out = o.cast<double>();
    return true;
}
template <size_t N>
bool get_opt_arr(const py::dict& d, const char* k, std::array<double, N>& out) {
    py::object o = d[k];
    if (o.is_none()) return false;
    out = arr<N>(o, k);
    return true;
}

// PolarAttitudeState's fields (estimators/polar_attitude.py) as a dict of the reference's types
py::dict state_dict(const State& s) {
    py::dict d;
    d["initialised"] = s.initialised;
    d["time_s"] = opt(s.has_time, s.time_s);
    d["q_P_from_body"] = np1(s.q_P_from_body);
    d["x_hat"] = np1(s.x_hat);
    d["P"] = np2(s.P.data(), NS, NS);
    d["gyro_prev_rad_s"] = opt_arr(s.has_gyro_prev, s.gyro_prev_rad_s);
    d["acc_n"] = s.acc_n;
    d["acc_dt_s"] = s.acc_dt_s;
    d["acc_f_sum_m_s2"] = np1(s.acc_f_sum_m_s2);
    d["acc_f_sq_sum_m2_s4"] = np1(s.acc_f_sq_sum_m2_s4);
    d["acc_down_sum"] = np1(s.acc_down_sum);
    d["acc_q_b0_from_b"] = np1(s.acc_q_b0_from_b);
    d["acc_C_BP_start"] = np2(s.acc_C_BP_start.data(), 3, 3);
    d["n_updates"] = s.n_updates;
    d["n_rejected"] = s.n_rejected;
    d["bias_prior_sigma_rad_s"] = opt(s.has_bias_prior_sigma, s.bias_prior_sigma_rad_s);
    d["gated_run"] = s.gated_run;
    d["reentry_wait"] = s.reentry_wait;
    d["z_prev_m_s2"] = opt_arr(s.has_z_prev, s.z_prev_m_s2);
    d["rest_gated_run"] = s.rest_gated_run;
    d["rest_f_sum_m_s2"] = np1(s.rest_f_sum_m_s2);
    d["rest_s"] = s.rest_s;
    d["n_relevels"] = s.n_relevels;
    d["sample_dt_s"] = opt(s.has_sample_dt, s.sample_dt_s);
    d["bias_rate_opened"] = s.bias_rate_opened;
    return d;
}

State state_from(const py::dict& d) {
    State s;
    s.initialised = d["initialised"].cast<bool>();
    s.has_time = get_opt(d, "time_s", s.time_s);
    s.q_P_from_body = arr<4>(d["q_P_from_body"], "q_P_from_body");
    s.x_hat = arr<NX>(d["x_hat"], "x_hat");
    s.P = arr<NS * NS>(d["P"], "P");
    s.has_gyro_prev = get_opt_arr(d, "gyro_prev_rad_s", s.gyro_prev_rad_s);
    s.acc_n = d["acc_n"].cast<long>();
    s.acc_dt_s = d["acc_dt_s"].cast<double>();
    s.acc_f_sum_m_s2 = arr<3>(d["acc_f_sum_m_s2"], "acc_f_sum_m_s2");
    if (d.contains("acc_f_sq_sum_m2_s4"))   // a record from before the field: zeros, as its default
        s.acc_f_sq_sum_m2_s4 = arr<3>(d["acc_f_sq_sum_m2_s4"], "acc_f_sq_sum_m2_s4");
    s.acc_down_sum = arr<3>(d["acc_down_sum"], "acc_down_sum");
    s.acc_q_b0_from_b = arr<4>(d["acc_q_b0_from_b"], "acc_q_b0_from_b");
    s.acc_C_BP_start = arr<9>(d["acc_C_BP_start"], "acc_C_BP_start");
    s.n_updates = d["n_updates"].cast<long>();
    s.n_rejected = d["n_rejected"].cast<long>();
    s.has_bias_prior_sigma = get_opt(d, "bias_prior_sigma_rad_s", s.bias_prior_sigma_rad_s);
    s.gated_run = d["gated_run"].cast<long>();
    s.reentry_wait = d["reentry_wait"].cast<long>();
    s.has_z_prev = get_opt_arr(d, "z_prev_m_s2", s.z_prev_m_s2);
    s.rest_gated_run = d["rest_gated_run"].cast<long>();
    s.rest_f_sum_m_s2 = arr<3>(d["rest_f_sum_m_s2"], "rest_f_sum_m_s2");
    s.rest_s = d["rest_s"].cast<double>();
    s.n_relevels = d["n_relevels"].cast<long>();
    s.has_sample_dt = get_opt(d, "sample_dt_s", s.sample_dt_s);
    if (d.contains("bias_rate_opened"))   // a record from before the field: False, as its default
        s.bias_rate_opened = d["bias_rate_opened"].cast<bool>();
    return s;
}

// A step's diagnostics: 0 for a plain sample (the common case: no object built), else
// (code, dt_s, fused, innovation (3,) or None, test_ratio, settle_ratio, accel_var_raised, why, relevel_rad)
py::object diag_out(const Diag& d) {
    if (d.code == SAMPLE) return py::int_(0);
    const bool upd = d.code == UPDATE;
    return py::make_tuple(d.code, d.dt_s, d.fused, upd ? py::object(np1(d.innovation_m_s2)) : py::object(py::none()),
                          d.test_ratio, d.settle_ratio, d.accel_var_raised_m2_s4, d.why, d.relevel_rad);
}

}  // namespace

void bind_polar(py::module_& m) {
    py::class_<Params>(m, "PolarAttitudeParams")
        .def(py::init([](const py::object& p) { return params_from(p); }), py::arg("params"),
             "estimators.polar_attitude.PolarAttitudeParams, converted once.");

    py::class_<State>(m, "PolarAttitude")
        .def(py::init([](const py::dict& state) { return state_from(state); }), py::arg("state"),
             "From a dict of PolarAttitudeState's fields (estimators/core.py builds it).")
        .def_static("init",
                    [](bool has_bias, double bx, double by, double bz, bool has_sigma, double sigma) {
                        return init(has_bias, {bx, by, bz}, has_sigma, sigma);
                    },
                    "polar_attitude_init (arguments checked by the caller)")
        .def_static("init_at",
                    [](const Params& p, double t, double roll, double pitch, double tilt_sigma, bool has_bias,
                       double bx, double by, double bz, bool has_sigma, double sigma) {
                        return init_at(t, roll, pitch, tilt_sigma, p, has_bias, {bx, by, bz}, has_sigma, sigma);
                    },
                    "polar_attitude_init_at (arguments checked by the caller)")
        .def("get_state", [](const State& s) { return state_dict(s); })
        .def("set_state", [](State& s, const py::dict& d) { s = state_from(d); })
        .def("step",
             [](State& s, const Params& p, double t, double wx, double wy, double wz, double fx, double fy,
                double fz) { return diag_out(step(s, t, {wx, wy, wz}, {fx, fy, fz}, p)); },
             "One sample (body frame): 0 or the diagnostics tuple (see diag_out).")
        .def("unseen", [](State& s, const Params& p, double unseen_s) { unseen(s, unseen_s, p); },
             "polar_attitude_unseen (unseen_s checked by the caller)")
        .def("estimate",
             [](const State& s) -> py::object {
                 if (!s.initialised) return py::none();
                 double roll, pitch;
                 Mat<2, 2> cov;
                 estimate(s, roll, pitch, cov);
                 return py::make_tuple(roll, pitch, np2(cov.data(), 2, 2),
                                       np1(V3{s.x_hat[0], s.x_hat[1], s.x_hat[2]}), np1(s.q_P_from_body));
             },
             "None before levelling, else (roll, pitch, cov (2, 2), gyro bias (3,), q_P_from_body (4,)).")
        .def_readonly("initialised", &State::initialised)
        .def_property_readonly("time_s", [](const State& s) { return opt(s.has_time, s.time_s); })
        .def_property_readonly("q_P_from_body", [](const State& s) { return np1(s.q_P_from_body); })
        .def_property_readonly("x_hat", [](const State& s) { return np1(s.x_hat); })
        .def_property_readonly("P", [](const State& s) { return np2(s.P.data(), NS, NS); })
        .def_readonly("n_updates", &State::n_updates)
        .def_readonly("n_rejected", &State::n_rejected)
        .def_readonly("n_relevels", &State::n_relevels);
}
