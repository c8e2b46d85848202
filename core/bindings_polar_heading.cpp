// estimators._core.PolarHeading: method C's heading filter (core/polar_heading.hpp) held in the core
// between filter steps. The Python face (estimators/core.py) keeps the reference's signatures
// (estimators/polar_heading.py): it checks the arguments as the reference does, converts the
// reference's params once (PolarHeadingParams), words the diagnostics, and converts the reference's
// PolarHeadingState to and from this object (get_state / set_state: dicts of the reference's field
// names) only when asked (a copy, a test, the zero-rate update at rest). A step reads the
// reference's HeadingInputs here; an input of a shape or type the filter does not take (not a number,
// an array of another shape, a zero quaternion) is handed back (None) untouched, and the Python face
// runs the reference on it, which answers as it answers.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <stdexcept>
#include <string>

#include "polar_heading.hpp"
#include "bindings_arrays.hpp"

namespace py = pybind11;
using namespace azimuthd;
using namespace azimuthd::polar_heading;
using ArrayC = py::array_t<double, py::array::c_style | py::array::forcecast>;

namespace {

double num(const py::handle& o, const char* name) { return o.attr(name).cast<double>(); }

Params params_from(const py::object& o) {
    Params p{};
    p.gyro_noise_rad_s_rt_hz = num(o, "gyro_noise_rad_s_rt_hz");
    p.gyro_bias_sigma_rad_s = num(o, "gyro_bias_sigma_rad_s");
    p.gyro_bias_tau_s = num(o, "gyro_bias_tau_s");
    p.vertical_rate_sigma_rad_s = num(o, "vertical_rate_sigma_rad_s");
    p.vertical_rate_tau_s = num(o, "vertical_rate_tau_s");
    p.attitude_error_tau_s = num(o, "attitude_error_tau_s");
    p.heading_process_floor_rad_s_rt_hz = num(o, "heading_process_floor_rad_s_rt_hz");
    p.mag_noise_gauss = num(o, "mag_noise_gauss");
    p.mag_heading_floor_rad = num(o, "mag_heading_floor_rad");
    p.min_horizontal_field_gauss = num(o, "min_horizontal_field_gauss");
    p.mag_update_period_s = num(o, "mag_update_period_s");
    p.mag_error_tau_s = num(o, "mag_error_tau_s");
    p.mag_error_turn_rad = num(o, "mag_error_turn_rad");
    p.consider_floor_fraction = num(o, "consider_floor_fraction");
    p.uncalibrated_hard_iron_gauss = num(o, "uncalibrated_hard_iron_gauss");
    p.uncalibrated_soft_iron = num(o, "uncalibrated_soft_iron");
    p.gate_chi2 = num(o, "gate_chi2");
    p.reset_after_s = num(o, "reset_after_s");
    p.max_abs_pitch_rad = num(o, "max_abs_pitch_rad");
    p.max_dt_s = num(o, "max_dt_s");
    p.unseen_rate_sigma_rad_s = num(o, "unseen_rate_sigma_rad_s");
    p.unseen_max_sigma_rad = num(o, "unseen_max_sigma_rad");
    return p;
}

// --- HeadingInputs -----------------------------------------------------------------------------------

// a number (anything float() takes, as math.isfinite does); false: not one
bool as_num(const py::handle& o, double& out) {
    if (o.is_none()) return false;
    double v = PyFloat_AsDouble(o.ptr());
    if (v == -1.0 && PyErr_Occurred()) {
        PyErr_Clear();
        return false;
    }
    out = v;
    return true;
}

// a float array of exactly this shape (1-D: c < 0); false: not one
bool as_arr(const py::handle& o, py::ssize_t r, py::ssize_t c, double* out) {
    auto a = ArrayC::ensure(o);
    if (!a) return false;
    if (c < 0 ? (a.ndim() != 1 || a.shape(0) != r) : (a.ndim() != 2 || a.shape(0) != r || a.shape(1) != c))
        return false;
    const double* d = a.data();
    for (py::ssize_t i = 0; i < a.size(); ++i) out[i] = d[i];
    return true;
}

// false: an input the filter does not take as it stands (the reference runs it)
bool read_inputs(const py::handle& u, Inputs& in) {
    if (!as_num(u.attr("time_s"), in.time_s) || !as_arr(u.attr("gyro_body_rad_s"), 3, -1, in.gyro.data()))
        return false;
    const py::object q = u.attr("q_P_from_body");
    in.has_q = !q.is_none();
    if (in.has_q) {
        if (!as_arr(q, 4, -1, in.q_P.data())) return false;
        const double n2 = dot4(in.q_P);
        // q_P / |q_P|: a zero or overflowing norm is the reference's to answer
        if (std::isfinite(in.q_P[0]) && std::isfinite(in.q_P[1]) && std::isfinite(in.q_P[2]) &&
            std::isfinite(in.q_P[3]) && !(std::isfinite(n2) && n2 > 0.0))
            return false;
        const int lv = PyObject_IsTrue(u.attr("level_with_roll_pitch").ptr());
        if (lv < 0) { PyErr_Clear(); return false; }
        in.level_with_roll_pitch = lv == 1;
        const py::object ca = u.attr("cov_att_body_rad2");
        in.has_cov_att = !ca.is_none();
        if (in.has_cov_att && !as_arr(ca, 3, 3, in.cov_att.data())) return false;
    } else {
        in.level_with_roll_pitch = false;
        in.has_cov_att = false;
    }
    // roll, pitch and their covariance: read by the Euler formulation and by the platform's
    // levelling with them; anything there is the reference's to answer
    const bool rp_used = !in.has_q || in.level_with_roll_pitch;
    if (!as_num(u.attr("roll_rad"), in.roll) || !as_num(u.attr("pitch_rad"), in.pitch)) {
        if (rp_used) return false;
        in.roll = in.pitch = NAN;
    }
    if (!as_arr(u.attr("cov_roll_pitch_rad2"), 2, 2, in.cov_rp.data())) {
        if (rp_used) return false;
        in.cov_rp = {NAN, NAN, NAN, NAN};
    }
    const py::object m = u.attr("mag_body_gauss");
    in.has_mag = !m.is_none();
    if (in.has_mag) {
        if (!as_arr(m, 3, -1, in.mag.data())) return false;
        if (!as_num(u.attr("declination_rad"), in.declination) ||
            !as_num(u.attr("declination_sigma_rad"), in.declination_sigma))
            return false;
        const py::object r = u.attr("mag_residual_sigma_gauss");
        in.has_residual = !r.is_none();
        if (in.has_residual && !as_num(r, in.residual_sigma)) return false;
        const py::object e = u.attr("field_model_ned_gauss");
        in.has_field_model = !e.is_none();
        if (in.has_field_model && !as_arr(e, 3, -1, in.field_model.data())) return false;
    } else {
        in.declination = in.declination_sigma = NAN;
        in.has_residual = false;
        in.residual_sigma = 0.0;
        in.has_field_model = false;
        in.field_model = {0.0, 0.0, 0.0};
    }
    return true;
}

// --- state <-> the reference's fields ----------------------------------------------------------------

py::array_t<double> vec(const double* x, py::ssize_t n) {
    py::array_t<double> a(n);
    double* o = a.mutable_data();
    for (py::ssize_t i = 0; i < n; ++i) o[i] = x[i];
    return a;
}

py::array_t<double> mat_n(const PH& P, int n) {
    py::array_t<double> a({static_cast<py::ssize_t>(n), static_cast<py::ssize_t>(n)});
    double* o = a.mutable_data();
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) o[i * n + j] = P[i * NM + j];
    return a;
}

using azimuthd::bind::opt;

bool get_opt(const py::dict& d, const char* k, double& out) {
    py::object o = d[k];
    if (o.is_none()) return false;
    out = o.cast<double>();
    return true;
}

py::dict state_dict(const State& s) {
    py::dict d;
    d["initialised"] = s.initialised;
    d["time_s"] = opt(s.has_time, s.time_s);
    d["x"] = vec(s.x.data(), s.n);
    d["P"] = mat_n(s.P, s.n);
    d["last_mag_time_s"] = opt(s.has_last_mag, s.last_mag_time_s);
    d["source_available"] = s.source_available;
    d["rejected_since_s"] = opt(s.has_rejected_since, s.rejected_since_s);
    d["n_fused"] = s.n_fused;
    d["n_rejected"] = s.n_rejected;
    d["n_resets"] = s.n_resets;
    d["r_corr_avg_rad2"] = opt(s.has_r_corr_avg, s.r_corr_avg_rad2);
    d["r_uncal_rad2"] = s.r_uncal_rad2;
    d["field_mismatch_gauss2"] = opt(s.has_field_mismatch, s.field_mismatch_gauss2);
    d["field_mismatch_time_s"] = opt(s.has_field_mismatch_time, s.field_mismatch_time_s);
    d["platform"] = s.platform;
    d["q_P_from_body"] = s.has_q ? py::object(vec(s.q_P_from_body.data(), 4)) : py::object(py::none());
    d["gyro_bias_prev_rad_s"] = s.has_gyro_bias_prev ? py::object(vec(s.gyro_bias_prev_rad_s.data(), 3))
                                                     : py::object(py::none());
    return d;
}

State state_from(const py::dict& d) {
    State s;
    s.initialised = d["initialised"].cast<bool>();
    s.has_time = get_opt(d, "time_s", s.time_s);
    auto x = ArrayC::ensure(d["x"]);
    if (!x || x.ndim() != 1 || (x.shape(0) != 4 && x.shape(0) != 5))
        throw std::invalid_argument("PolarHeadingState.x: 4 or 5 values expected");
    s.n = static_cast<int>(x.shape(0));
    for (int i = 0; i < s.n; ++i) s.x[i] = x.data()[i];
    auto P = ArrayC::ensure(d["P"]);
    if (!P || P.ndim() != 2 || P.shape(0) != s.n || P.shape(1) != s.n)
        throw std::invalid_argument("PolarHeadingState.P: len(x) x len(x) expected");
    for (int i = 0; i < s.n; ++i)
        for (int j = 0; j < s.n; ++j) s.P[i * NM + j] = P.data()[i * s.n + j];
    s.has_last_mag = get_opt(d, "last_mag_time_s", s.last_mag_time_s);
    s.source_available = d["source_available"].cast<bool>();
    s.has_rejected_since = get_opt(d, "rejected_since_s", s.rejected_since_s);
    s.n_fused = d["n_fused"].cast<long>();
    s.n_rejected = d["n_rejected"].cast<long>();
    s.n_resets = d["n_resets"].cast<long>();
    s.has_r_corr_avg = get_opt(d, "r_corr_avg_rad2", s.r_corr_avg_rad2);
    s.r_uncal_rad2 = d["r_uncal_rad2"].cast<double>();
    // absent from a dict of an older PolarHeadingState: None
    if (d.contains("field_mismatch_gauss2"))
        s.has_field_mismatch = get_opt(d, "field_mismatch_gauss2", s.field_mismatch_gauss2);
    if (d.contains("field_mismatch_time_s"))
        s.has_field_mismatch_time = get_opt(d, "field_mismatch_time_s", s.field_mismatch_time_s);
    s.platform = d["platform"].cast<bool>();
    py::object q = d["q_P_from_body"];
    s.has_q = !q.is_none();
    if (s.has_q && !as_arr(q, 4, -1, s.q_P_from_body.data()))
        throw std::invalid_argument("PolarHeadingState.q_P_from_body: 4 values expected");
    py::object g = d["gyro_bias_prev_rad_s"];
    s.has_gyro_bias_prev = !g.is_none();
    if (s.has_gyro_bias_prev && !as_arr(g, 3, -1, s.gyro_bias_prev_rad_s.data()))
        throw std::invalid_argument("PolarHeadingState.gyro_bias_prev_rad_s: 3 values expected");
    return s;
}

// A step's diagnostics: 0/1 for a plain step (HeadingDiag(source_available=0/1): no object built),
// else (code, source_available, dt_s, H, z, nu, S, test_ratio, reset_jump, why)
py::object diag_out(const Diag& d) {
    if (d.code == PLAIN) return py::int_(d.source_available ? 1 : 0);
    return py::make_tuple(d.code, d.source_available, d.dt_s, d.H, d.z, d.nu, d.S, d.ratio, d.reset_jump, d.why);
}

}  // namespace

void bind_polar_heading(py::module_& m) {
    py::class_<Params>(m, "PolarHeadingParams")
        .def(py::init([](const py::object& p) { return params_from(p); }), py::arg("params"),
             "estimators.polar_heading.PolarHeadingParams, converted once.");

    py::class_<State>(m, "PolarHeading")
        .def(py::init([](const py::dict& state) { return state_from(state); }), py::arg("state"),
             "From a dict of PolarHeadingState's fields (estimators/core.py builds it).")
        .def_static("init",
                    [](const Params& p, bool has_heading, double heading, double sigma, bool has_bias, double by,
                       double bz) { return init(has_heading, heading, sigma, has_bias, by, bz, p); },
                    "polar_heading_init (arguments checked by the caller)")
        .def("get_state", [](const State& s) { return state_dict(s); })
        .def("set_state", [](State& s, const py::dict& d) { s = state_from(d); })
        .def("step",
             [](State& s, const Params& p, const py::handle& u) -> py::object {
                 Inputs in{};
                 if (!read_inputs(u, in)) return py::none();
                 const Diag d = step(s, in, p);
                 if (d.code == BAD_DECLINATION)
                     throw std::invalid_argument("declination_rad must be finite when a magnetometer sample is given");
                 return diag_out(d);
             },
             "One HeadingInputs: 0/1 or the diagnostics tuple (see diag_out); None: an input the core does "
             "not take (the state untouched; the reference answers it).")
        .def("unseen", [](State& s, const Params& p, double unseen_s) { unseen(s, unseen_s, p); },
             "polar_heading_unseen (unseen_s checked by the caller)")
        .def("estimate",
             [](const State& s) -> py::object {
                 if (!s.initialised) return py::none();
                 double heading, var;
                 estimate(s, heading, var);
                 return py::make_tuple(heading, var, s.source_available);
             },
             "None before the first heading, else (heading, published variance, source_available).")
        .def("attitude",
             [](const State& s, double heading) -> py::object {
                 if (!(s.platform && s.initialised && s.has_q)) return py::none();
                 const Q4 q = attitude(s, heading);
                 return vec(q.data(), 4);
             },
             "polar_heading_attitude for a finite heading (None outside the platform formulation).")
        .def_readonly("initialised", &State::initialised)
        .def_property_readonly("time_s", [](const State& s) { return opt(s.has_time, s.time_s); })
        .def_property_readonly("x", [](const State& s) { return vec(s.x.data(), s.n); })
        .def_property_readonly("P", [](const State& s) { return mat_n(s.P, s.n); })
        .def_property_readonly("last_mag_time_s", [](const State& s) { return opt(s.has_last_mag, s.last_mag_time_s); })
        .def_readonly("source_available", &State::source_available)
        .def_property_readonly("rejected_since_s",
                               [](const State& s) { return opt(s.has_rejected_since, s.rejected_since_s); })
        .def_readonly("n_fused", &State::n_fused)
        .def_readonly("n_rejected", &State::n_rejected)
        .def_readonly("n_resets", &State::n_resets)
        .def_property_readonly("r_corr_avg_rad2", [](const State& s) { return opt(s.has_r_corr_avg, s.r_corr_avg_rad2); })
        .def_readonly("r_uncal_rad2", &State::r_uncal_rad2)
        .def_property_readonly("field_mismatch_gauss2",
                               [](const State& s) { return opt(s.has_field_mismatch, s.field_mismatch_gauss2); })
        .def_property_readonly("field_mismatch_time_s",
                               [](const State& s) { return opt(s.has_field_mismatch_time, s.field_mismatch_time_s); })
        .def_readonly("platform", &State::platform)
        .def_property_readonly("q_P_from_body", [](const State& s) -> py::object {
            return s.has_q ? py::object(vec(s.q_P_from_body.data(), 4)) : py::object(py::none());
        })
        .def_property_readonly("gyro_bias_prev_rad_s", [](const State& s) -> py::object {
            return s.has_gyro_bias_prev ? py::object(vec(s.gyro_bias_prev_rad_s.data(), 3)) : py::object(py::none());
        });
}
