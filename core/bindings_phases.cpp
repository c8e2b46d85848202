// estimators._core.Phases: the flight phases (core/phases.hpp, service/phases.py phase_step) held
// in the core between IMU samples. The Python face (service/phases_core.py, HeldPhaseState) keeps the
// reference's signature, converts the reference's PhaseParams once per params object (PhaseParams
// here, with Python's own texts of the thresholds its events print with :g) and the reference's
// PhaseState to and from this object (get_state / set_state: dicts of the reference's field names,
// the levelling accumulators packed as core/bindings.cpp packs them) only when asked. A step reads
// the gyro and accel (float64 (3,) arrays), the time (a float) and the FlightEvidence here; an input
// of another type or shape is handed back (None) untouched and the Python face runs the reference
// on it, which answers as it answers.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstring>
#include <stdexcept>
#include <string>

#include "phases.hpp"

namespace py = pybind11;
using namespace azimuthd;
using namespace azimuthd::phases;

namespace {

constexpr py::ssize_t PACKED = LEVELLING_PACKED_SIZE;  // core/levelling.hpp levelling_pack

LevellingAcc unpack_acc(const py::handle& h) {
    auto arr = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(h);
    if (!arr || arr.ndim() != 1 || arr.shape(0) != PACKED)
        throw std::invalid_argument("a packed levelling accumulator must be 38 floats");
    return levelling_unpack(arr.data());
}

py::array_t<double> packed(const LevellingAcc& s) {
    py::array_t<double> out(PACKED);
    levelling_pack(s, out.mutable_data());
    return out;
}

py::array_t<double> arr3(const double* v) {
    py::array_t<double> out(3);
    std::memcpy(out.mutable_data(), v, 3 * sizeof(double));
    return out;
}

py::object opt(const Opt& v) { return v ? py::object(py::float_(*v)) : py::object(py::none()); }

Opt opt_in(const py::handle& h) { return h.is_none() ? Opt() : Opt(h.cast<double>()); }

void vec3_in(const py::handle& h, double out[3]) {
    py::sequence s = py::reinterpret_borrow<py::sequence>(h);
    if (py::len(s) != 3) throw std::invalid_argument("expected 3 numbers");
    for (int i = 0; i < 3; ++i) out[i] = s[i].cast<double>();
}

// a passing LevellingResult: (roll, pitch, gyro bias (3), accel mean (3), roll sigma, pitch sigma,
// samples, duration, accel std, tilt noise, gyro bias sigma)
py::object result_out(const std::optional<LevResult>& r) {
    if (!r) return py::none();
    return py::make_tuple(r->roll_rad, r->pitch_rad, arr3(r->gyro_bias_rad_s), arr3(r->accel_mean_m_s2), r->roll_sigma_rad,
                          r->pitch_sigma_rad, static_cast<long long>(r->samples), r->duration_s, r->accel_std_m_s2,
                          r->tilt_noise_rad, r->gyro_bias_sigma_rad_s);
}

std::optional<LevResult> result_in(const py::handle& h) {
    if (h.is_none()) return std::nullopt;
    if (!h.attr("ok").cast<bool>() || h.attr("noisy").cast<bool>())
        throw std::invalid_argument("the phases keep passing levellings only (ok True, noisy False)");
    LevResult r;
    r.ok = true;
    r.why = OK;
    r.roll_rad = h.attr("roll_rad").cast<double>();
    r.pitch_rad = h.attr("pitch_rad").cast<double>();
    vec3_in(h.attr("gyro_bias_rad_s"), r.gyro_bias_rad_s);
    vec3_in(h.attr("accel_mean_m_s2"), r.accel_mean_m_s2);
    r.roll_sigma_rad = h.attr("roll_sigma_rad").cast<double>();
    r.pitch_sigma_rad = h.attr("pitch_sigma_rad").cast<double>();
    r.samples = h.attr("samples").cast<double>();
    r.duration_s = h.attr("duration_s").cast<double>();
    r.accel_std_m_s2 = h.attr("accel_std_m_s2").cast<double>();
    r.tilt_noise_rad = h.attr("tilt_noise_rad").cast<double>();
    r.gyro_bias_sigma_rad_s = h.attr("gyro_bias_sigma_rad_s").cast<double>();
    return r;
}

std::string g_text(double v) { return py::str("{:g}").format(v).cast<std::string>(); }

double num(const py::handle& o, const char* name) { return o.attr(name).cast<double>(); }

LevParams lev_from(const py::handle& lp) {
    LevParams p;
    p.min_samples = num(lp, "min_samples");
    p.min_duration_s = num(lp, "min_duration_s");
    p.max_accel_std_m_s2 = num(lp, "max_accel_std_m_s2");
    p.max_gyro_std_rad_s = num(lp, "max_gyro_std_rad_s");
    p.max_tilt_noise_rad = num(lp, "max_tilt_noise_rad");
    p.max_gyro_sem_rad_s = num(lp, "max_gyro_sem_rad_s");
    p.batch_s = num(lp, "batch_s");
    p.min_batches = num(lp, "min_batches");
    p.gravity_tolerance_m_s2 = num(lp, "gravity_tolerance_m_s2");
    p.accel_bias_sigma_m_s2 = num(lp, "accel_bias_sigma_m_s2");
    p.t_min_samples = py::str(lp.attr("min_samples")).cast<std::string>();  // f"{min_samples}"
    p.t_min_duration_s = py::str("{:g}").format(lp.attr("min_duration_s")).cast<std::string>();
    p.t_max_accel_std_m_s2 = py::str("{:g}").format(lp.attr("max_accel_std_m_s2")).cast<std::string>();
    p.t_max_gyro_std_deg = g_text(p.max_gyro_std_rad_s * RAD_TO_DEG);
    p.t_max_tilt_noise_deg = g_text(p.max_tilt_noise_rad * RAD_TO_DEG);
    p.t_max_gyro_sem_deg = g_text(p.max_gyro_sem_rad_s * RAD_TO_DEG);
    return p;
}

Params params_from(const py::object& o) {
    Params p;
    p.still_seconds = num(o, "still_seconds");
    p.detect_accel_m_s2 = num(o, "detect_accel_m_s2");
    p.detect_hold_s = num(o, "detect_hold_s");
    p.boost_window_s = num(o, "boost_window_s");
    p.lev = lev_from(o.attr("levelling"));
    p.lev_short = p.lev;  // service.phases._launch: dc_replace(levelling, min_samples=20, min_duration_s=0.3)
    p.lev_short.min_samples = 20;
    p.lev_short.min_duration_s = 0.3;
    p.lev_short.t_min_samples = "20";
    p.lev_short.t_min_duration_s = g_text(0.3);
    const py::object f = o.attr("in_flight");
    p.airspeed_m_s = num(f, "airspeed_m_s");
    p.alt_rate_m_s = num(f, "alt_rate_m_s");
    p.hold_s = num(f, "hold_s");
    p.not_still_s = num(f, "not_still_s");
    p.accel_norm_m_s2 = num(f, "accel_norm_m_s2");
    p.accel_norm_hold_s = num(f, "accel_norm_hold_s");
    p.decide_s = num(f, "decide_s");
    const py::object v = o.attr("vehicle");
    if (v.is_none()) {
        p.vehicle = NO_VEHICLE;
    } else {
        const std::string name = v.cast<std::string>();
        const char* names[] = {"launcher", "hand", "runway", "multicopter", "vtol"};
        p.vehicle = NO_VEHICLE - 1;
        for (int i = 0; i < 5; ++i)
            if (name == names[i]) p.vehicle = i;
        if (p.vehicle < NO_VEHICLE) throw std::invalid_argument("vehicle must be one of launcher, hand, runway, "
                                                                "multicopter, vtol or None, got " + name);
        p.vehicle_name = name;
    }
    vec3_in(o.attr("forward_sensor"), p.fwd);
    p.detect_started_in_flight = o.attr("detect_started_in_flight").cast<bool>();
    p.filter_tau_s = num(o, "filter_tau_s");
    p.runway_accel_m_s2 = num(o, "runway_accel_m_s2");
    p.runway_hold_s = num(o, "runway_hold_s");
    p.runway_max_roll_s = num(o, "runway_max_roll_s");
    p.liftoff_accel_m_s2 = num(o, "liftoff_accel_m_s2");
    p.liftoff_hold_s = num(o, "liftoff_hold_s");
    p.liftoff_climb_m_s = num(o, "liftoff_climb_m_s");
    p.impulse_forward_share = num(o, "impulse_forward_share");
    p.moved_rad = num(o, "moved_rad");
    p.t_airspeed_m_s = g_text(p.airspeed_m_s);
    p.t_alt_rate_m_s = g_text(p.alt_rate_m_s);
    p.t_accel_norm_m_s2 = g_text(p.accel_norm_m_s2);
    p.t_detect_accel_m_s2 = g_text(p.detect_accel_m_s2);
    p.t_runway_accel_m_s2 = g_text(p.runway_accel_m_s2);
    p.t_liftoff_accel_m_s2 = g_text(p.liftoff_accel_m_s2);
    p.t_liftoff_climb_m_s = g_text(p.liftoff_climb_m_s);
    p.t_runway_max_roll_s = g_text(p.runway_max_roll_s);
    return p;
}

// a float64 (3,) array's values; false: not one (the reference answers it)
bool read3(PyObject* o, double out[3]) {
    if (!PyObject_CheckBuffer(o)) return false;
    Py_buffer b;
    if (PyObject_GetBuffer(o, &b, PyBUF_FORMAT | PyBUF_STRIDES) != 0) {
        PyErr_Clear();
        return false;
    }
    const bool ok = b.ndim == 1 && b.shape[0] == 3 && b.itemsize == 8 && b.format && std::strcmp(b.format, "d") == 0;
    if (ok)
        for (int i = 0; i < 3; ++i) std::memcpy(&out[i], static_cast<const char*>(b.buf) + i * b.strides[0], 8);
    PyBuffer_Release(&b);
    return ok;
}

int tri(PyObject* o) { return o == Py_True ? 1 : (o == Py_False ? 0 : -1); }

// a number or None (NaN); false: neither (the reference answers it)
bool number_or_none(PyObject* o, double& out) {
    if (o == Py_None) { out = NAN; return true; }
    if (!(PyFloat_Check(o) || PyLong_Check(o))) return false;
    out = PyFloat_AsDouble(o);
    if (out == -1.0 && PyErr_Occurred()) { PyErr_Clear(); return false; }
    return true;
}

bool evidence_in(const py::handle& h, Evidence& ev) {
    if (h.is_none()) return true;
    // interned once, never released (no Python object outlives the interpreter as a static)
    static PyObject* const keys[5] = {PyUnicode_InternFromString("armed"), PyUnicode_InternFromString("fc_reports_flying"),
                                      PyUnicode_InternFromString("fc_landed"), PyUnicode_InternFromString("airspeed_m_s"),
                                      PyUnicode_InternFromString("alt_rate_m_s")};
    PyObject* v[5];
    for (int i = 0; i < 5; ++i) {
        v[i] = PyObject_GetAttr(h.ptr(), keys[i]);
        if (!v[i]) {
            for (int j = 0; j < i; ++j) Py_DECREF(v[j]);
            PyErr_Clear();
            return false;
        }
    }
    ev.armed = tri(v[0]);
    ev.fc_reports_flying = tri(v[1]);
    ev.fc_landed = tri(v[2]);
    const bool ok = number_or_none(v[3], ev.airspeed_m_s) && number_or_none(v[4], ev.alt_rate_m_s);
    for (PyObject* o : v) Py_DECREF(o);
    return ok;
}

int phase_in(const std::string& name) {
    for (int i = 0; i < 4; ++i)
        if (name == phase_name(i)) return i;
    throw std::invalid_argument("phase must be one of boot, pre-launch, launch, in-flight, got " + name);
}

py::dict get_state(const State& s) {
    py::dict d;
    d["phase"] = phase_name(s.phase);
    d["block"] = packed(s.block);
    d["block_start_s"] = opt(s.block_start_s);
    d["level"] = result_out(s.level);
    d["level_block"] = s.level_block ? py::object(packed(*s.level_block)) : py::object(py::none());
    d["level_time_s"] = opt(s.level_time_s);
    d["above_since_s"] = opt(s.above_since_s);
    d["below_since_s"] = opt(s.below_since_s);
    d["launch_time_s"] = opt(s.launch_time_s);
    d["launch_evidence"] = s.launch_evidence;
    d["start_time_s"] = opt(s.start_time_s);
    d["started_in_flight"] = s.started_in_flight;
    d["in_flight_evidence"] = s.in_flight_evidence;
    d["airspeed_since_s"] = opt(s.airspeed_since_s);
    d["fc_flying_since_s"] = opt(s.fc_flying_since_s);
    d["alt_rate_since_s"] = opt(s.alt_rate_since_s);
    d["accel_norm_since_s"] = opt(s.accel_norm_since_s);
    d["fc_air_since_s"] = opt(s.fc_air_since_s);
    d["fc_seen_landed"] = s.fc_seen_landed;
    d["not_still_total_s"] = s.not_still_total_s;
    d["pending_level"] = result_out(s.pending_level);
    d["pending_block"] = s.pending_block ? py::object(packed(*s.pending_block)) : py::object(py::none());
    d["noisy_run"] = packed(s.noisy_run);
    d["block_passed_s"] = opt(s.block_passed_s);
    d["last_block_mean_m_s2"] =
        s.has_last_block_mean ? py::object(arr3(s.last_block_mean_m_s2)) : py::object(py::none());
    d["time_prev_s"] = opt(s.time_prev_s);
    d["f_lp_m_s2"] = s.has_f_lp ? py::object(py::make_tuple(s.f_lp_m_s2[0], s.f_lp_m_s2[1], s.f_lp_m_s2[2]))
                                : py::object(py::none());
    d["run_since_s"] = opt(s.run_since_s);
    d["climb_since_s"] = opt(s.climb_since_s);
    d["impulse_sum_m_s2"] = arr3(s.impulse_sum_m_s2);
    d["impulse_refused"] = s.impulse_refused;
    d["disarmed_refused"] = s.disarmed_refused;
    d["moved_vec_rad"] = py::make_tuple(s.moved_vec_rad[0], s.moved_vec_rad[1], s.moved_vec_rad[2]);
    d["moved_rad"] = s.moved_rad;
    return d;
}

void set_state(State& s, const py::dict& d) {
    State n;
    n.phase = phase_in(d["phase"].cast<std::string>());
    n.block = unpack_acc(d["block"]);
    n.block_start_s = opt_in(d["block_start_s"]);
    n.level = result_in(d["level"]);
    if (!d["level_block"].is_none()) n.level_block = unpack_acc(d["level_block"]);
    n.level_time_s = opt_in(d["level_time_s"]);
    n.above_since_s = opt_in(d["above_since_s"]);
    n.below_since_s = opt_in(d["below_since_s"]);
    n.launch_time_s = opt_in(d["launch_time_s"]);
    n.launch_evidence = d["launch_evidence"].cast<std::string>();
    n.start_time_s = opt_in(d["start_time_s"]);
    n.started_in_flight = d["started_in_flight"].cast<bool>();
    n.in_flight_evidence = d["in_flight_evidence"].cast<std::string>();
    n.airspeed_since_s = opt_in(d["airspeed_since_s"]);
    n.fc_flying_since_s = opt_in(d["fc_flying_since_s"]);
    n.alt_rate_since_s = opt_in(d["alt_rate_since_s"]);
    n.accel_norm_since_s = opt_in(d["accel_norm_since_s"]);
    n.fc_air_since_s = opt_in(d["fc_air_since_s"]);
    n.fc_seen_landed = d["fc_seen_landed"].cast<bool>();
    n.not_still_total_s = d["not_still_total_s"].cast<double>();
    n.pending_level = result_in(d["pending_level"]);
    if (!d["pending_block"].is_none()) n.pending_block = unpack_acc(d["pending_block"]);
    n.noisy_run = unpack_acc(d["noisy_run"]);
    n.block_passed_s = opt_in(d["block_passed_s"]);
    if (!d["last_block_mean_m_s2"].is_none()) {
        n.has_last_block_mean = true;
        vec3_in(d["last_block_mean_m_s2"], n.last_block_mean_m_s2);
    }
    n.time_prev_s = opt_in(d["time_prev_s"]);
    if (!d["f_lp_m_s2"].is_none()) {
        n.has_f_lp = true;
        vec3_in(d["f_lp_m_s2"], n.f_lp_m_s2);
    }
    n.run_since_s = opt_in(d["run_since_s"]);
    n.climb_since_s = opt_in(d["climb_since_s"]);
    vec3_in(d["impulse_sum_m_s2"], n.impulse_sum_m_s2);
    n.impulse_refused = d["impulse_refused"].cast<bool>();
    n.disarmed_refused = d["disarmed_refused"].cast<bool>();
    vec3_in(d["moved_vec_rad"], n.moved_vec_rad);
    n.moved_rad = d["moved_rad"].cast<double>();
    // the reference's own invariants, which the core's step relies on
    if (n.level && !n.level_block) throw std::invalid_argument("a levelling without its block (level_block None)");
    if (n.pending_level.has_value() != n.pending_block.has_value())
        throw std::invalid_argument("pending_level and pending_block must be both None or both set");
    if (n.phase == LAUNCH && !n.launch_time_s) throw std::invalid_argument("phase launch without launch_time_s");
    n.level_version = s.level_version + 1;
    s = n;
}

}  // namespace

void bind_phases(py::module_& m) {
    py::class_<Params>(m, "PhaseParams", "service.phases.PhaseParams, converted once (with Python's texts)")
        .def(py::init([](const py::object& o) { return params_from(o); }), py::arg("params"));

    py::class_<State>(m, "Phases", "service.phases.PhaseState held in the core")
        .def(py::init([](const py::dict& d) {
                 State s;
                 set_state(s, d);
                 return s;
             }),
             py::arg("state"), "From the reference's fields (get_state's dict).")
        .def("get_state", &get_state, "The reference's fields (levelling accumulators packed, results as tuples).")
        .def("set_state", &set_state, py::arg("state"))
        .def(
            "step",
            [](State& s, const Params& p, const py::handle& gyro, const py::handle& accel, const py::handle& time,
               const py::handle& evidence) -> py::object {
                double g[3], a[3];
                Evidence ev;
                if (!PyFloat_Check(time.ptr()) || !read3(gyro.ptr(), g) || !read3(accel.ptr(), a) ||
                    !evidence_in(evidence, ev))
                    return py::none();
                const double t = PyFloat_AS_DOUBLE(time.ptr());
                Events events;
                phase_step(s, g, a, t, p, ev, events);
                if (events.empty()) return py::int_(s.phase);
                py::list out(events.size());
                for (size_t i = 0; i < events.size(); ++i)
                    out[i] = py::make_tuple(py::str(events[i].first), py::str(events[i].second));
                return std::move(out);
            },
            py::arg("params"), py::arg("gyro_rad_s"), py::arg("accel_m_s2"), py::arg("time_s"), py::arg("evidence"),
            "One IMU sample: the phase's code (0 boot .. 3 in-flight) when no event, else the events "
            "[(kind, text)]; None: an input the core does not take (the state untouched; the reference answers it).")
        .def_readonly("phase", &State::phase)
        .def_readonly("level_version", &State::level_version)
        .def_readonly("started_in_flight", &State::started_in_flight)
        .def_property_readonly("block_start_s", [](const State& s) { return opt(s.block_start_s); })
        .def_property_readonly("block_passed_s", [](const State& s) { return opt(s.block_passed_s); })
        .def_property_readonly("launch_time_s", [](const State& s) { return opt(s.launch_time_s); })
        .def_property_readonly("level_time_s", [](const State& s) { return opt(s.level_time_s); })
        .def_property_readonly("start_time_s", [](const State& s) { return opt(s.start_time_s); })
        .def_readonly("moved_rad", &State::moved_rad)
        .def_readonly("launch_evidence", &State::launch_evidence)
        .def_readonly("in_flight_evidence", &State::in_flight_evidence)
        .def_property_readonly("level", [](const State& s) { return result_out(s.level); })
        .def_property_readonly("level_block", [](const State& s) {
            return s.level_block ? py::object(packed(*s.level_block)) : py::object(py::none());
        });
}
