// estimators._core: the Pipeline's per-sample hot path (core/hot_path.hpp).
// - SampleState: the Pipeline's per-sample fields (service/pipeline.py reads and writes them as
//   attributes: last_time_fc_s, _acc_gyro, _out ...), the one state Python's on_imu and hot_run share;
// - AzimuthRun: method A's per-sample state for one run, from and back to the AzimuthState;
// - hot_run: the quiet samples of a batch. The Python face is estimators/core.py (hot-path section).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cmath>
#include <stdexcept>
#include <string>

#include "hot_path.hpp"
#include "filter_chain.hpp"  // mag_hard_iron_residual
#include "mag_disturbance.hpp"

namespace py = pybind11;
using namespace azimuthd;
using ArrayC = py::array_t<double, py::array::c_style | py::array::forcecast>;

namespace {

void take(const py::handle& obj, double* out, py::ssize_t n, const char* name) {
    ArrayC a = ArrayC::ensure(obj);
    if (!a || a.size() != n)
        throw std::invalid_argument(std::string(name) + ": " + std::to_string(n) + " numbers expected");
    const double* d = a.data();
    for (py::ssize_t i = 0; i < n; ++i) out[i] = d[i];
}

ArrayC give(const double* x, py::ssize_t n) {
    ArrayC a(n);
    for (py::ssize_t i = 0; i < n; ++i) a.mutable_data()[i] = x[i];
    return a;
}

py::object opt_float(bool has, double v) { return has ? py::object(py::float_(v)) : py::object(py::none()); }

py::object output_state_class() {  // looked up once (an import per call cost ~2 us a sample)
    static py::object* cls =
        new py::object(py::module_::import("estimators.output_propagation").attr("OutputState"));
    return *cls;
}

// n floats from a tuple, list or array (a tuple element by element: no numpy array built)
void take_seq(const py::handle& obj, double* out, py::ssize_t n, const char* name) {
    if (py::isinstance<py::tuple>(obj)) {
        py::tuple t = py::reinterpret_borrow<py::tuple>(obj);
        if (static_cast<py::ssize_t>(t.size()) != n)
            throw std::invalid_argument(std::string(name) + ": " + std::to_string(n) + " numbers expected");
        for (py::ssize_t i = 0; i < n; ++i) out[i] = t[static_cast<size_t>(i)].cast<double>();
        return;
    }
    take(obj, out, n, name);
}

// Method A's output configuration (core/azimuth_output.hpp) from estimators/core.py azimuth_output_cfg's
// tuple: (has_solution, C_isf_af, C_sf_body, C_nf_af, C_af_isf, c_gyro (12), P_psi_c (15 x 15), arw2,
// launch_time_s, fm2, last_sample_s, sigma_b, u_sf or None, aligned, du_dbeta_sf (3 x 2) or None, c_tilt (2)).
AzimuthOutputCfg azimuth_cfg_in(const py::tuple& t) {
    if (t.size() != 16) throw std::invalid_argument("azimuth output configuration: 16 items expected");
    AzimuthOutputCfg c;
    c.set = true;
    c.has_solution = t[0].cast<bool>();
    take(t[1], c.C_isf_af.data(), 9, "C_isf_af");
    take(t[2], c.C_sf_body.data(), 9, "C_sf_body");
    if (c.has_solution) {
        take(t[3], c.C_nf_af.data(), 9, "C_nf_af");
        take(t[4], c.C_af_isf.data(), 9, "C_af_isf");
        take(t[5], c.c_gyro, 12, "c_gyro");
        ArrayC P = ArrayC::ensure(t[6]);
        if (!P || P.ndim() != 2 || P.shape(0) != 15 || P.shape(1) != 15)
            throw std::invalid_argument("P_psi_c: 15 x 15 expected");
        c.nP = 15;
        c.P.assign(P.data(), P.data() + 225);
        c.arw2 = t[7].cast<double>();
        c.launch_time_s = t[8].cast<double>();
        c.fm2 = t[9].cast<double>();
        c.last_sample_s = t[10].cast<double>();
        c.sigma_b = t[11].cast<double>();
        c.has_u = !t[12].is_none();
        if (c.has_u) take(t[12], c.u_sf.data(), 3, "u_sf");
        c.aligned = t[13].cast<bool>();
        c.has_du = !t[14].is_none();
        if (c.has_du) take(t[14], c.du, 6, "du_dbeta_sf");
        take(t[15], c.c_tilt, 2, "c_tilt");
    }
    return c;
}

// (roll, pitch, q_nav_from_body, heading, heading_sigma, azimuth, azimuth_sigma, launch_azimuth)
py::tuple azimuth_numbers_out(const AzimuthOutputNumbers& o) {
    return py::make_tuple(o.roll, o.pitch, give(o.q.data(), 4), o.heading, o.heading_sigma, o.azimuth,
                          o.azimuth_sigma, o.launch_azimuth);
}

py::object out_get(const SampleState& h) {
    if (!h.out.has) return py::none();
    const OutputProp& o = h.out;
    py::object inc = o.has_inc ? py::object(py::make_tuple(o.inc[0], o.inc[1], o.inc[2])) : py::object(py::none());
    return output_state_class()(py::make_tuple(o.q[0], o.q[1], o.q[2], o.q[3]), o.time_s, inc);
}

void out_set(SampleState& h, const py::object& v) {
    if (v.is_none()) {
        h.out.has = false;
        return;
    }
    OutputProp o;
    o.has = true;
    take_seq(v.attr("q_nav_from_body"), o.q, 4, "OutputState.q_nav_from_body");
    o.time_s = v.attr("time_s").cast<double>();
    py::object inc = v.attr("increment_prev");
    o.has_inc = !inc.is_none();
    if (o.has_inc) take_seq(inc, o.inc, 3, "OutputState.increment_prev");
    h.out = o;
}

py::object rest_state_class() {  // estimators.declination.RestState, looked up once
    static py::object* cls = new py::object(py::module_::import("estimators.declination").attr("RestState"));
    return *cls;
}

py::object rest_get(const RestAcc& r) {
    return rest_state_class()(r.n, give(r.gyro_mean, 3), give(r.gyro_m2, 3), give(r.accel_mean, 3),
                              give(r.accel_m2, 3), give(r.mag_mean, 3), give(r.mag_m2, 3));
}

RestAcc rest_in(const py::handle& v) {
    RestAcc r;
    r.n = v.attr("n").cast<long long>();
    take(v.attr("gyro_mean_rad_s"), r.gyro_mean, 3, "RestState.gyro_mean_rad_s");
    take(v.attr("gyro_m2"), r.gyro_m2, 3, "RestState.gyro_m2");
    take(v.attr("accel_mean_m_s2"), r.accel_mean, 3, "RestState.accel_mean_m_s2");
    take(v.attr("accel_m2"), r.accel_m2, 3, "RestState.accel_m2");
    take(v.attr("mag_mean_gauss"), r.mag_mean, 3, "RestState.mag_mean_gauss");
    take(v.attr("mag_m2"), r.mag_m2, 3, "RestState.mag_m2");
    return r;
}

ArrayC pending_out(const GroundState& g) {
    ArrayC out({static_cast<py::ssize_t>(g.pending.size()), py::ssize_t(7)});
    double* d = out.mutable_data();
    for (const auto& e : g.pending)
        for (int k = 0; k < 7; ++k) *d++ = e[k];
    return out;
}

ArrayC levelling_out(const LevellingAcc& s) {
    ArrayC out(LEVELLING_PACKED_SIZE);
    levelling_pack(s, out.mutable_data());
    return out;
}

// A's pre-launch part into the core: the delay line ((k, 7) rows: time, gyro, accel), the packed
// levelling accumulator (core/levelling.hpp levelling_pack) and the delay
void azimuth_in(GroundState& g, const py::object& pending, const py::object& levelling, double buffer_s) {
    ArrayC p = ArrayC::ensure(pending);
    if (!p || p.ndim() != 2 || p.shape(1) != 7)
        throw std::invalid_argument("pending: the delay line as (k, 7) rows (time, gyro, accel) expected");
    ArrayC l = ArrayC::ensure(levelling);
    if (!l || l.ndim() != 1 || l.shape(0) != LEVELLING_PACKED_SIZE)
        throw std::invalid_argument("levelling: a packed levelling accumulator (38 floats) expected");
    if (!std::isfinite(buffer_s)) throw std::invalid_argument("buffer_s: a finite delay (s) expected");
    g.pending.clear();
    const double* d = p.data();
    for (py::ssize_t i = 0; i < p.shape(0); ++i, d += 7) g.pending.push_back({d[0], d[1], d[2], d[3], d[4], d[5], d[6]});
    g.a_levelling = levelling_unpack(l.data());
    g.buffer_s = buffer_s;
    g.a_held = true;
}

py::tuple ground_get(const GroundState& g) {
    return py::make_tuple(g.a_held, g.buffer_s, pending_out(g), levelling_out(g.a_levelling), rest_get(g.rest),
                          rest_get(g.candidate));
}

py::tuple sample_state_get(const SampleState& h) {
    return py::make_tuple(opt_float(h.has_last_time, h.last_time_fc_s), opt_float(h.has_last_rx, h.last_rx_s),
                          h.filter_due_s, give(h.acc_gyro, 3), give(h.acc_accel, 3), h.acc_n,
                          h.has_acc_mag ? py::object(give(h.acc_mag, 3)) : py::object(py::none()), out_get(h),
                          give(h.out_bias_body, 3), opt_float(h.has_out_sample, h.out_rx_s),
                          h.has_out_sample ? py::object(give(h.out_gyro, 3)) : py::object(py::none()));
}


// --- the bound hot path (service/hot_path.py sample_step / batch_steps) ----------------------------
// One Python number as a double (false: not a number; the sample then goes to on_imu, which says why).
bool read_num(PyObject* o, double& v) {
    if (PyFloat_CheckExact(o)) {
        v = PyFloat_AS_DOUBLE(o);
        return true;
    }
    v = PyFloat_AsDouble(o);
    if (v == -1.0 && PyErr_Occurred()) {
        PyErr_Clear();
        return false;
    }
    return true;
}

using ArrayExact = py::array_t<double, py::array::c_style>;

// Three doubles from a float64 (3,) array (what the link's ImuSample carries); false for anything
// else (the sample then goes to on_imu: the reference handles every other form)
bool read3(const py::handle& o, double out[3]) {
    if (!ArrayExact::check_(o)) return false;
    auto a = py::reinterpret_borrow<ArrayExact>(o);
    if (a.ndim() != 1 || a.shape(0) != 3) return false;
    const double* d = a.data();
    out[0] = d[0];
    out[1] = d[1];
    out[2] = d[2];
    return true;
}

// Three doubles from any array-like (take's conversion when it is not a float64 (3,) array)
void take3(const py::handle& o, double out[3], const char* name) {
    if (!read3(o, out)) take(o, out, 3, name);
}

// An ImuSample's fields as one IMU_RECORD row (time_fc, time_rx, gyro, accel, mag (NaN: none)) and
// whether its source carries int16 raw counts (service/input_checks.py _INT16_SOURCES); false: not
// numbers in the link's form (on_imu takes it).
bool sample_row(const py::handle& s, double r[11], bool& int16) {
    static const py::str k_t("time_fc_s"), k_rx("time_rx_s"), k_g("gyro_rad_s"), k_a("accel_m_s2"),
        k_m("mag_gauss"), k_src("source");
    PyObject* o = s.ptr();
    py::object t = py::reinterpret_steal<py::object>(PyObject_GetAttr(o, k_t.ptr()));
    py::object rx = py::reinterpret_steal<py::object>(PyObject_GetAttr(o, k_rx.ptr()));
    py::object g = py::reinterpret_steal<py::object>(PyObject_GetAttr(o, k_g.ptr()));
    py::object a = py::reinterpret_steal<py::object>(PyObject_GetAttr(o, k_a.ptr()));
    py::object m = py::reinterpret_steal<py::object>(PyObject_GetAttr(o, k_m.ptr()));
    py::object src = py::reinterpret_steal<py::object>(PyObject_GetAttr(o, k_src.ptr()));
    if (!t || !rx || !g || !a || !m || !src) {
        PyErr_Clear();
        return false;
    }
    if (!read_num(t.ptr(), r[0]) || !read_num(rx.ptr(), r[1]) || !read3(g, r + 2) || !read3(a, r + 5)) return false;
    if (m.is_none()) {
        r[8] = r[9] = r[10] = NAN;
    } else if (!read3(m, r + 8)) {
        return false;
    }
    int16 = PyUnicode_Check(src.ptr()) && (PyUnicode_CompareWithASCIIString(src.ptr(), "RAW_IMU") == 0 ||
                                           PyUnicode_CompareWithASCIIString(src.ptr(), "SCALED_IMU") == 0);
    return true;
}

// A Pipeline's hot path with what stays fixed bound once: its per-sample state, its input checks,
// C_body_from_sensor, the two integration limits and the filter period (fixed from the Pipeline's
// config). A call passes what the Pipeline replaces between samples: its strapdown, method A's run,
// the gyro bias (and on the ground the phases, their params, the ground state and the evidence).
struct BoundHotPath {
    py::object state_ref, checks_ref;  // kept alive
    SampleState* h = nullptr;
    InputChecks* ic = nullptr;
    HotInputs in{};
};

// the bound inputs with this call's gyro bias and source form
HotInputs call_inputs(const BoundHotPath& b, const py::handle& gyro_bias, bool int16_source) {
    HotInputs in = b.in;
    take3(gyro_bias, in.gyro_bias, "gyro_bias_rad_s");
    in.int16_source = int16_source;
    return in;
}

// HP_QUIET: the sample was quiet and is committed; HP_UNREAD: not read (not in the link's form, its
// input check not run: on_imu takes it); else the input checks' verdict on it (it stopped the run).
enum : int { HP_QUIET = -1, HP_UNREAD = -2 };

GroundInputs ground_inputs(const py::object& phase_state, const py::object& phase_params, const py::object& ground,
                           const py::object& evidence) {
    GroundInputs gi;
    gi.ph = phase_state.cast<phases::State*>();
    gi.pp = phase_params.cast<const phases::Params*>();
    gi.gs = ground.is_none() ? nullptr : ground.cast<GroundState*>();
    if (gi.ph == nullptr || gi.pp == nullptr)
        throw std::invalid_argument("phases, phase_params: the held _core.Phases and its _core.PhaseParams expected");
    if (gi.ph->phase != phases::PRE_LAUNCH) throw std::invalid_argument("phases: a ground run starts in phase pre-launch");
    if (gi.gs != nullptr && !gi.gs->a_held)
        throw std::invalid_argument("ground: method A's pre-launch part is not held there");
    py::tuple e = evidence.cast<py::tuple>();
    if (e.size() != 8)
        throw std::invalid_argument("evidence: (armed, fc_reports_flying, fc_landed, has_air, air_time_s, "
                                    "air_max_age_s, airspeed_m_s, alt_rate_m_s) expected");
    gi.armed = e[0].cast<int>();
    gi.fc_reports_flying = e[1].cast<int>();
    gi.fc_landed = e[2].cast<int>();
    gi.has_air = e[3].cast<bool>();
    gi.air_time_s = e[4].cast<double>();
    gi.air_max_age_s = e[5].cast<double>();
    gi.airspeed_m_s = e[6].cast<double>();
    gi.alt_rate_m_s = e[7].cast<double>();
    return gi;
}


}  // namespace

void bind_hot_path(py::module_& m) {
    py::class_<SampleState>(m, "SampleState")
        .def(py::init<>())
        .def_property("last_time_fc_s", [](const SampleState& h) { return opt_float(h.has_last_time, h.last_time_fc_s); },
                      [](SampleState& h, const py::object& v) {
                          h.has_last_time = !v.is_none();
                          h.last_time_fc_s = h.has_last_time ? v.cast<double>() : 0.0;
                      })
        .def_property("last_rx_s", [](const SampleState& h) { return opt_float(h.has_last_rx, h.last_rx_s); },
                      [](SampleState& h, const py::object& v) {
                          h.has_last_rx = !v.is_none();
                          h.last_rx_s = h.has_last_rx ? v.cast<double>() : 0.0;
                      })
        .def_readwrite("filter_due_s", &SampleState::filter_due_s)
        .def_property("acc_gyro", [](const SampleState& h) { return give(h.acc_gyro, 3); },
                      [](SampleState& h, const py::object& v) { take(v, h.acc_gyro, 3, "acc_gyro"); })
        .def_property("acc_accel", [](const SampleState& h) { return give(h.acc_accel, 3); },
                      [](SampleState& h, const py::object& v) { take(v, h.acc_accel, 3, "acc_accel"); })
        .def_readwrite("acc_n", &SampleState::acc_n)
        .def_property("acc_mag",
                      [](const SampleState& h) {
                          return h.has_acc_mag ? py::object(give(h.acc_mag, 3)) : py::object(py::none());
                      },
                      [](SampleState& h, const py::object& v) {
                          h.has_acc_mag = !v.is_none();
                          if (h.has_acc_mag) take(v, h.acc_mag, 3, "acc_mag");
                      })
        .def_property("out", &out_get, &out_set)
        .def_property("out_bias_body_rad_s", [](const SampleState& h) { return give(h.out_bias_body, 3); },
                      [](SampleState& h, const py::object& v) { take(v, h.out_bias_body, 3, "out_bias_body_rad_s"); })
        .def_property("out_rx_s", [](const SampleState& h) { return opt_float(h.has_out_sample, h.out_rx_s); },
                      [](SampleState& h, const py::object& v) {
                          h.has_out_sample = !v.is_none();
                          h.out_rx_s = h.has_out_sample ? v.cast<double>() : 0.0;
                      })
        .def_property("out_gyro_s",
                      [](const SampleState& h) {
                          return h.has_out_sample ? py::object(give(h.out_gyro, 3)) : py::object(py::none());
                      },
                      [](SampleState& h, const py::object& v) {
                          if (!v.is_none()) take(v, h.out_gyro, 3, "out_gyro_s");
                      })
        .def("accumulate",
             [](SampleState& h, const py::object& g, const py::object& a, const py::object& m, double t,
                double filter_period_s) {
                 double gv[3], av[3], mv[3];
                 take(g, gv, 3, "gyro_rad_s");
                 take(a, av, 3, "accel_m_s2");
                 if (!m.is_none()) take(m, mv, 3, "mag_gauss");
                 return accumulate(h, gv, av, m.is_none() ? nullptr : mv, t, filter_period_s);
             },
             py::arg("gyro_rad_s"), py::arg("accel_m_s2"), py::arg("mag_gauss"), py::arg("time_s"),
             py::arg("filter_period_s"), "service/hot_path.SampleState.accumulate's twin.")
        .def("turn_output",
             [](SampleState& h, double t, const py::object& gb, double max_dt_s, double rx, const py::object& g) {
                 if (!h.out.has) return;
                 double gbv[3], gv[3];
                 take(gb, gbv, 3, "gyro_body_rad_s");
                 take(g, gv, 3, "gyro_rad_s");
                 turn_output(h, t, gbv, max_dt_s, rx, gv);
             },
             py::arg("time_s"), py::arg("gyro_body_rad_s"), py::arg("max_dt_s"), py::arg("time_rx_s"),
             py::arg("gyro_rad_s"), "service/hot_path.SampleState.turn_output's twin.")
        .def("out_snapshot",
             [](const SampleState& h) -> py::object {
                 if (!h.out.has) return py::none();
                 const OutputProp& o = h.out;
                 return py::make_tuple(py::make_tuple(o.q[0], o.q[1], o.q[2], o.q[3]), o.time_s,
                                       opt_float(h.has_out_sample, h.out_rx_s),
                                       h.has_out_sample ? py::object(py::make_tuple(h.out_gyro[0], h.out_gyro[1],
                                                                                    h.out_gyro[2]))
                                                        : py::object(py::none()));
             },
             "service/hot_path.SampleState.out_snapshot's twin: (q_nav_from_body, time_s, out_rx_s, out_gyro_s "
             "as a tuple) of the output attitude, None without one; no numpy array built.")
        .def("get_state", &sample_state_get, "Every field, as a tuple (the pickle form).")
        .def(py::pickle(&sample_state_get, [](const py::tuple& s) {
            if (s.size() != 11) throw std::invalid_argument("SampleState: 11 fields expected");
            SampleState h;
            py::object self = py::cast(SampleState());  // setters through a temporary Python object
            self.attr("last_time_fc_s") = s[0];
            self.attr("last_rx_s") = s[1];
            self.attr("filter_due_s") = s[2];
            self.attr("acc_gyro") = s[3];
            self.attr("acc_accel") = s[4];
            self.attr("acc_n") = s[5];
            self.attr("acc_mag") = s[6];
            self.attr("out") = s[7];
            self.attr("out_bias_body_rad_s") = s[8];
            self.attr("out_rx_s") = s[9];
            self.attr("out_gyro_s") = s[10];
            h = self.cast<SampleState>();
            return h;
        }));

    py::class_<AzimuthRun>(m, "AzimuthRun")
        .def(py::init<>(), "Method A not stepped by the run.")
        .def(py::init([](const py::object& q, bool has_prev, double time_prev_s, const py::object& gyro_prev,
                         const py::object& G, const py::object& C, const py::object& bias, double max_dt_s,
                         double launch_time_s, double mag_skip_after_launch_s, double mag_decimation_s,
                         long long max_fit_samples, long long n_samples, double last_mag_s, double last_solve_s,
                         double solve_period_s, double next_solve_s, bool submit_phase) {
                 AzimuthRun a;
                 a.active = true;
                 take(q, a.sd.q_ref_from_sensor, 4, "q_ref_from_sensor");
                 a.sd.has_prev = has_prev;
                 a.sd.time_prev_s = time_prev_s;
                 if (has_prev) take(gyro_prev, a.sd.gyro_prev_rad_s, 3, "gyro_prev_rad_s");
                 take(G, a.G, 36, "G_gyro");
                 take(C, a.C, 9, "C_isf_sf");
                 take(bias, a.bias, 3, "gyro_bias_rad_s");
                 a.max_dt_s = max_dt_s;
                 a.launch_time_s = launch_time_s;
                 a.mag_skip_after_launch_s = mag_skip_after_launch_s;
                 a.mag_decimation_s = mag_decimation_s;
                 a.max_fit_samples = max_fit_samples;
                 a.n_samples = n_samples;
                 a.last_mag_s = last_mag_s;
                 a.last_solve_s = last_solve_s;
                 a.solve_period_s = solve_period_s;
                 a.next_solve_s = next_solve_s;
                 a.submit_phase = submit_phase;
                 return a;
             }),
             py::arg("q_ref_from_sensor"), py::arg("has_prev"), py::arg("time_prev_s"), py::arg("gyro_prev_rad_s"),
             py::arg("G_gyro"), py::arg("C_isf_sf"), py::arg("gyro_bias_rad_s"), py::arg("max_dt_s"),
             py::arg("launch_time_s"), py::arg("mag_skip_after_launch_s"), py::arg("mag_decimation_s"),
             py::arg("max_fit_samples"), py::arg("n_samples"), py::arg("last_mag_s"), py::arg("last_solve_s"),
             py::arg("solve_period_s"), py::arg("next_solve_s"), py::arg("submit_phase"))
        .def_readonly("active", &AzimuthRun::active)
        .def_readonly("n_samples", &AzimuthRun::n_samples, "len(AzimuthState.samples) with the run's stored ones.")
        .def_readwrite("submit_blocked", &AzimuthRun::submit_blocked,
                       "The solver is busy (its submit would be refused): a sample with a submit due stays quiet.")
        .def("step",
             [](AzimuthRun& a, double t, const ArrayC& gyro, const py::object& mag) {
                 if (!a.active) throw std::invalid_argument("AzimuthRun.step: the run does not step method A");
                 if (gyro.size() != 3) throw std::invalid_argument("gyro_rad_s: 3 numbers expected");
                 double m[3];
                 const double* mp = nullptr;
                 if (!mag.is_none()) {
                     take(mag, m, 3, "mag_gauss");
                     if (std::isfinite(m[0]) && std::isfinite(m[1]) && std::isfinite(m[2])) mp = m;
                 }
                 StrapdownState a_sd{};
                 double aG[36], aC[9];
                 bool store = false;
                 if (!azimuth_try(a, t, gyro.data(), mp, a_sd, aG, aC, store)) return false;
                 azimuth_commit(a, t, mp, a_sd, aG, aC, store);
                 return true;
             },
             py::arg("time_s"), py::arg("gyro_rad_s"), py::arg("mag_gauss"),
             "Method A's step of one sample (Pipeline._step_azimuth in flight) when it is quiet: True and committed; "
             "False (nothing changed) when it is not integrated or a solve or a solver submit is due on it.")
        .def_property_readonly("output_set", [](const AzimuthRun& a) { return a.out.set; })
        .def("set_output", [](AzimuthRun& a, const py::tuple& cfg) { a.out = azimuth_cfg_in(cfg); }, py::arg("cfg"),
             "What A's output needs beside G and C (estimators/core.py azimuth_output_cfg), fixed for the run.")
        .def("output",
             [](const AzimuthRun& a, double t) {
                 if (!a.out.set) throw std::invalid_argument("AzimuthRun.output before set_output");
                 return azimuth_numbers_out(azimuth_output_numbers(a.out, a.G, a.C, t));
             },
             py::arg("time_s"), "The numbers of A's output at the run's last sample (time_s): see azimuth_output_numbers.")
        .def("result",
             [](AzimuthRun& a) {
                 ArrayC G({py::ssize_t(3), py::ssize_t(12)}), C({py::ssize_t(3), py::ssize_t(3)});
                 for (int k = 0; k < 36; ++k) G.mutable_data()[k] = a.G[k];
                 for (int k = 0; k < 9; ++k) C.mutable_data()[k] = a.C[k];
                 const py::ssize_t nr = static_cast<py::ssize_t>(a.rec.size() / AzimuthRun::REC);
                 ArrayC rec({nr, py::ssize_t(AzimuthRun::REC)});
                 for (size_t k = 0; k < a.rec.size(); ++k) rec.mutable_data()[k] = a.rec[k];
                 a.rec.clear();
                 return py::make_tuple(give(a.sd.q_ref_from_sensor, 4), a.sd.time_prev_s, give(a.sd.gyro_prev_rad_s, 3),
                                       G, C, a.last_mag_s, rec);
             },
             "(q, time_prev_s, gyro_prev_rad_s, G (3, 12), C_isf_sf, last_mag_s, stored samples (k, 49): time, h "
             "(3), C_sf_from_isf (9), G (36)); the stored samples are handed over (cleared here).");

    py::class_<GroundState>(m, "GroundState",
                            "The Pipeline's ground (pre-launch) state (core/ground.hpp): method A's delay line and "
                            "levelling while held here, method E's rest data.")
        .def(py::init<>())
        .def_readonly("a_held", &GroundState::a_held, "Method A's pre-launch part is held here.")
        .def("set_azimuth", &azimuth_in, py::arg("pending"), py::arg("levelling"), py::arg("buffer_s"),
             "Method A's pre-launch part in: the delay line as (k, 7) rows (time, gyro (3), accel (3)), the packed "
             "levelling accumulator, AzimuthParams.prelaunch_buffer_s.")
        .def("take_azimuth",
             [](GroundState& g) {
                 if (!g.a_held) throw std::invalid_argument("method A's pre-launch part is not held here");
                 py::tuple out = py::make_tuple(pending_out(g), levelling_out(g.a_levelling));
                 g.a_held = false;
                 g.pending.clear();
                 g.a_levelling = LevellingAcc();
                 return out;
             },
             "Method A's pre-launch part out (no longer held here): (delay line (k, 7), packed levelling).")
        .def_property("rest", [](const GroundState& g) { return rest_get(g.rest); },
                      [](GroundState& g, const py::object& v) { g.rest = rest_in(v); },
                      "The Pipeline's rest (estimators.declination.RestState; a new record per read).")
        .def_property("rest_candidate", [](const GroundState& g) { return rest_get(g.candidate); },
                      [](GroundState& g, const py::object& v) { g.candidate = rest_in(v); },
                      "The rest data of the still block filling (estimators.declination.RestState).")
        .def("step",
             [](GroundState& g, const py::object& gyro, const py::object& accel, const py::object& mag, double t,
                bool block_ended, bool block_passed) {
                 if (!g.a_held) throw std::invalid_argument("method A's pre-launch part is not held here");
                 double gv[3], av[3], mv[3];
                 take(gyro, gv, 3, "gyro_rad_s");
                 take(accel, av, 3, "accel_m_s2");
                 if (!mag.is_none()) take(mag, mv, 3, "mag_gauss");
                 ground_step(g, gv, av, mag.is_none() ? nullptr : mv, t, block_ended, block_passed);
             },
             py::arg("gyro_rad_s"), py::arg("accel_m_s2"), py::arg("mag_gauss"), py::arg("time_s"),
             py::arg("block_ended"), py::arg("block_passed"),
             "service/pipeline.py _step_azimuth's pre-launch branch for one sample (core/ground.hpp ground_step).")
        .def("get_state", &ground_get, "(a_held, buffer_s, delay line, packed levelling, rest, rest candidate).")
        .def(py::pickle(&ground_get, [](const py::tuple& s) {
            if (s.size() != 6) throw std::invalid_argument("GroundState: 6 fields expected");
            GroundState g;
            if (s[0].cast<bool>()) azimuth_in(g, s[2], s[3], s[1].cast<double>());
            g.buffer_s = s[1].cast<double>();
            g.rest = rest_in(s[4]);
            g.candidate = rest_in(s[5]);
            return g;
        }));

    py::class_<BoundHotPath>(m, "HotPath",
                             "A Pipeline's hot path with its fixed inputs bound once (service/hot_path.py): the "
                             "per-sample state, the input checks, C_body_from_sensor, the strapdown's and the output "
                             "attitude's max_dt_s and the filter period. `flight`/`ground` take one ImuSample, "
                             "`run`/`run_ground` a batch's rows, as hot_run does with every argument.")
        .def(py::init([](const py::object& state, const py::object& checks, const py::object& C_bs,
                         double strapdown_max_dt_s, double out_max_dt_s, double filter_period_s) {
                 BoundHotPath b;
                 b.h = state.cast<SampleState*>();   // None casts to nullptr: refused
                 b.ic = checks.cast<InputChecks*>();
                 if (b.h == nullptr) throw std::invalid_argument("state: a _core.SampleState expected");
                 if (b.ic == nullptr) throw std::invalid_argument("checks: a _core.InputChecks expected");
                 b.state_ref = state;
                 b.checks_ref = checks;
                 take(C_bs, b.in.C_bs, 9, "C_body_from_sensor");
                 if (!(std::isfinite(strapdown_max_dt_s) && std::isfinite(out_max_dt_s) && filter_period_s > 0.0 &&
                       std::isfinite(filter_period_s)))
                     throw std::invalid_argument("HotPath: finite max_dt_s and a positive filter period expected");
                 b.in.strapdown_max_dt_s = strapdown_max_dt_s;
                 b.in.out_max_dt_s = out_max_dt_s;
                 b.in.filter_period_s = filter_period_s;
                 return b;
             }),
             py::arg("state"), py::arg("checks"), py::arg("C_body_from_sensor"), py::arg("strapdown_max_dt_s"),
             py::arg("out_max_dt_s"), py::arg("filter_period_s"))
        .def("flight",
             [](BoundHotPath& b, const py::handle& sample, const py::object& strapdown, AzimuthRun& a,
                const py::handle& gyro_bias) {
                 double r[11];
                 bool int16 = false;
                 if (!sample_row(sample, r, int16)) return static_cast<int>(HP_UNREAD);
                 StrapdownState* sd = strapdown.is_none() ? nullptr : strapdown.cast<StrapdownState*>();
                 HotInputs in = call_inputs(b, gyro_bias, int16);
                 int verdict = 0;
                 bool checked = false;
                 long handled = 0;
                 const long stop = hot_run(*b.h, *b.ic, sd, a, in, r, 1, 11, 0, verdict, checked, handled);
                 return stop == 1 ? static_cast<int>(HP_QUIET) : verdict;
             },
             py::arg("sample"), py::arg("strapdown"), py::arg("azimuth"), py::arg("gyro_bias_rad_s"),
             "One ImuSample in flight (hot_run on its row): HOT_QUIET (-1) taken; HOT_UNREAD (-2) not in the "
             "link's form, unchecked (on_imu takes it); else its input-check verdict (on_imu takes it with that).")
        .def("ground",
             [](BoundHotPath& b, const py::handle& sample, const py::object& phase_state, const py::object& phase_params,
                const py::object& ground, const py::object& evidence, const py::handle& gyro_bias) {
                 double r[11];
                 bool int16 = false;
                 if (!sample_row(sample, r, int16)) return static_cast<int>(HP_UNREAD);
                 const GroundInputs gi = ground_inputs(phase_state, phase_params, ground, evidence);
                 HotInputs in = call_inputs(b, gyro_bias, int16);
                 int verdict = 0;
                 bool checked = false;
                 long handled = 0;
                 const long stop = ground_run(*b.h, *b.ic, gi, in, r, 1, 11, 0, verdict, checked, handled);
                 return stop == 1 ? static_cast<int>(HP_QUIET) : verdict;
             },
             py::arg("sample"), py::arg("phases"), py::arg("phase_params"), py::arg("ground"), py::arg("evidence"),
             py::arg("gyro_bias_rad_s"), "One ImuSample on the ground (ground_run on its row); `flight`'s codes.")
        .def("run",
             [](BoundHotPath& b, const ArrayC& rows, long start, const py::object& strapdown, AzimuthRun& a,
                const py::handle& gyro_bias, bool int16_source) {
                 if (rows.ndim() != 2 || rows.shape(1) < 11)
                     throw std::invalid_argument("rows: IMU_RECORD rows as an (N, >= 11) float64 block expected");
                 const long n = static_cast<long>(rows.shape(0));
                 if (start < 0 || start > n) throw std::invalid_argument("start: outside the rows");
                 StrapdownState* sd = strapdown.is_none() ? nullptr : strapdown.cast<StrapdownState*>();
                 HotInputs in = call_inputs(b, gyro_bias, int16_source);
                 int verdict = 0;
                 bool checked = false;
                 long handled = 0;
                 const long stop = hot_run(*b.h, *b.ic, sd, a, in, rows.data(), n, static_cast<long>(rows.shape(1)),
                                           start, verdict, checked, handled);
                 return py::make_tuple(stop, verdict, checked, handled);
             },
             py::arg("rows"), py::arg("start"), py::arg("strapdown"), py::arg("azimuth"), py::arg("gyro_bias_rad_s"),
             py::arg("int16_source"), "hot_run's flight run with the bound inputs: (stop, verdict, checked, handled).")
        .def("run_ground",
             [](BoundHotPath& b, const ArrayC& rows, long start, const py::object& phase_state,
                const py::object& phase_params, const py::object& ground, const py::object& evidence,
                const py::handle& gyro_bias, bool int16_source) {
                 if (rows.ndim() != 2 || rows.shape(1) < 11)
                     throw std::invalid_argument("rows: IMU_RECORD rows as an (N, >= 11) float64 block expected");
                 const long n = static_cast<long>(rows.shape(0));
                 if (start < 0 || start > n) throw std::invalid_argument("start: outside the rows");
                 const GroundInputs gi = ground_inputs(phase_state, phase_params, ground, evidence);
                 HotInputs in = call_inputs(b, gyro_bias, int16_source);
                 int verdict = 0;
                 bool checked = false;
                 long handled = 0;
                 const long stop = ground_run(*b.h, *b.ic, gi, in, rows.data(), n, static_cast<long>(rows.shape(1)),
                                              start, verdict, checked, handled);
                 return py::make_tuple(stop, verdict, checked, handled);
             },
             py::arg("rows"), py::arg("start"), py::arg("phases"), py::arg("phase_params"), py::arg("ground"),
             py::arg("evidence"), py::arg("gyro_bias_rad_s"), py::arg("int16_source"),
             "hot_run's ground run with the bound inputs: (stop, verdict, checked, handled).");
    m.def("mag_hard_iron_residual",
          [](const MagDisturbance& md, const py::handle& mag_body, const py::handle& q_P_from_body,
             double soft_iron) -> py::object {
              V3 mb;
              Q4 q;
              take3(mag_body, mb.data(), "mag_body_gauss");
              take(q_P_from_body, q.data(), 4, "q_P_from_body");
              double out = 0.0;
              if (!mag_hard_iron_residual(md, q, mb, soft_iron, out)) return py::none();
              return py::float_(out);
          },
          py::arg("mag_disturbance"), py::arg("mag_body_gauss"), py::arg("q_P_from_body"), py::arg("soft_iron"),
          "service/pipeline.py Pipeline._mag_hard_iron_residual's twin on the held _core.MagDisturbance: the "
          "per-axis sigma (gauss) the learnt hard iron leaves in the heading plus the uncompensated soft iron; "
          "None without the hard iron's covariance or a horizontal field.");

    m.attr("HOT_QUIET") = static_cast<int>(HP_QUIET);
    m.attr("HOT_UNREAD") = static_cast<int>(HP_UNREAD);

    m.attr("HOT_STOP_END") = static_cast<int>(HS_END);
    m.def("azimuth_output_numbers",
          [](const py::tuple& cfg, const ArrayC& G, const ArrayC& C, double t) {
              if (G.size() != 36 || C.size() != 9) throw std::invalid_argument("G (3, 12) and C (3, 3) expected");
              return azimuth_numbers_out(azimuth_output_numbers(azimuth_cfg_in(cfg), G.data(), C.data(), t));
          },
          py::arg("cfg"), py::arg("G_gyro"), py::arg("C_isf_sf"), py::arg("time_s"),
          "Method A's output numbers (core/azimuth_output.hpp; estimators/azimuth.py azimuth_output_numbers): (roll, pitch, "
          "q_nav_from_body, heading, heading_sigma, azimuth, azimuth_sigma, launch_azimuth), NaN where none.");
    m.def("hot_run",
          [](SampleState& h, InputChecks& ic, py::object strapdown, AzimuthRun& a, const ArrayC& rows, long start,
             const py::object& gyro_bias, const py::object& C_bs, double strapdown_max_dt_s, double out_max_dt_s,
             double filter_period_s, bool int16_source, const py::object& phase_state, const py::object& phase_params,
             const py::object& ground, const py::object& evidence) {
              if (rows.ndim() != 2 || rows.shape(1) < 11)
                  throw std::invalid_argument("rows: IMU_RECORD rows as an (N, >= 11) float64 block expected");
              StrapdownState* sd = strapdown.is_none() ? nullptr : strapdown.cast<StrapdownState*>();
              HotInputs in{};
              take(gyro_bias, in.gyro_bias, 3, "gyro_bias_rad_s");
              take(C_bs, in.C_bs, 9, "C_body_from_sensor");
              in.strapdown_max_dt_s = strapdown_max_dt_s;
              in.out_max_dt_s = out_max_dt_s;
              in.filter_period_s = filter_period_s;
              in.int16_source = int16_source;
              const long n = static_cast<long>(rows.shape(0));
              if (start < 0 || start > n) throw std::invalid_argument("start: outside the rows");
              int verdict = 0;
              bool checked = false;
              long handled = 0;
              long stop;
              if (phase_state.is_none()) {
                  stop = hot_run(h, ic, sd, a, in, rows.data(), n, static_cast<long>(rows.shape(1)), start, verdict,
                                 checked, handled);
              } else {  // the ground run
                  const GroundInputs gi = ground_inputs(phase_state, phase_params, ground, evidence);
                  stop = ground_run(h, ic, gi, in, rows.data(), n, static_cast<long>(rows.shape(1)), start, verdict,
                                    checked, handled);
              }
              return py::make_tuple(stop, verdict, checked, handled);
          },
          py::arg("state"), py::arg("checks"), py::arg("strapdown"), py::arg("azimuth"), py::arg("rows"),
          py::arg("start"), py::arg("gyro_bias_rad_s"), py::arg("C_body_from_sensor"), py::arg("strapdown_max_dt_s"),
          py::arg("out_max_dt_s"), py::arg("filter_period_s"), py::arg("int16_source"), py::arg("phases") = py::none(),
          py::arg("phase_params") = py::none(), py::arg("ground") = py::none(), py::arg("evidence") = py::none(),
          "The quiet rows from `start`: (first row not handled (N: all), its input-check verdict, whether its "
          "check ran, rows handled). In flight by default; with `phases` (the held _core.Phases in phase "
          "pre-launch), its _core.PhaseParams, the GroundState (None: method A off) and the evidence tuple "
          "(armed, fc_reports_flying, fc_landed as -1 None / 0 / 1, has_air, air_time_s, air_max_age_s, "
          "airspeed_m_s, alt_rate_m_s, NaN: none) the ground run (core/hot_path.hpp ground_run; strapdown and "
          "azimuth unused).");
}
