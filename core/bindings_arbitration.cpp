// estimators._core.arbitrate: the heading arbitration (core/heading_arbitration.hpp), one pure step.
// The Python face (service/arbitration_core.py) keeps the reference's signature
// (service/heading_arbitration.py arbitrate): it checks time_s as the reference does, converts the
// reference's params once (ArbitrationParams), and turns what comes back into the reference's
// ArbitrationState, ArbitrationOutput, ArbitrationEvent and aiding records. The aiding records whose
// code the core chose are made here (tuple.__new__ of the record type the face hands in, as
// AidingRecord._make makes them), worded as the reference words them (printf's %.Nf: correctly
// rounded, as Python's format); a record whose code is the caller's (a reading not valid or
// inconsistent) is worded and checked by the face. The reference's ArbitrationState and
// SourceReadings are read as they stand; a value the step does not take as it stands (a number that
// is not a Python float or a small int, a name or group that is not a str, two readings of one name,
// sources that are not a tuple, a sequence that is not a list or tuple) gives None, untouched, and
// the Python face runs the reference on it, which answers as it answers.
#include <pybind11/pybind11.h>

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "heading_arbitration.hpp"
#include "bindings_arrays.hpp"

namespace py = pybind11;
using namespace azimuthd::arbitration;

namespace {

PyObject* key(const char* name) { return PyUnicode_InternFromString(name); }

// a borrowed-to-owned attribute (nullptr: none, the error cleared)
py::object attr(PyObject* o, PyObject* name) {
    PyObject* v = PyObject_GetAttr(o, name);
    if (!v) {
        PyErr_Clear();
        return py::object();
    }
    return py::reinterpret_steal<py::object>(v);
}

// a number as the reference computes with it: a Python float (numpy's float64 is one), or an int
// small enough that its square is exact in a double (the reference squares ints exactly)
bool as_num(PyObject* o, double& out) {
    if (PyFloat_Check(o)) {
        out = PyFloat_AS_DOUBLE(o);
        return true;
    }
    if (PyLong_CheckExact(o)) {
        const double v = PyLong_AsDouble(o);
        if (v == -1.0 && PyErr_Occurred()) {
            PyErr_Clear();
            return false;
        }
        if (std::abs(v) > 67108864.0) return false;  // 2^26
        out = v;
        return true;
    }
    return false;
}

// None or a number
bool as_opt(PyObject* o, bool& has, double& out) {
    has = o != Py_None;
    return !has || as_num(o, out);
}

bool as_str(PyObject* o, std::string& out) {
    if (!PyUnicode_Check(o)) return false;
    Py_ssize_t n = 0;
    const char* s = PyUnicode_AsUTF8AndSize(o, &n);
    if (!s) {
        PyErr_Clear();
        return false;
    }
    out.assign(s, static_cast<std::size_t>(n));
    return true;
}

bool as_truth(PyObject* o, bool& out) {
    const int t = PyObject_IsTrue(o);
    if (t < 0) {
        PyErr_Clear();
        return false;
    }
    out = t == 1;
    return true;
}

Params params_from(const py::object& o) {
    Params p{};
    p.gate_chi2 = o.attr("gate_chi2").cast<double>();
    p.max_age_s = o.attr("max_age_s").cast<double>();
    p.max_sigma_rad = o.attr("max_sigma_rad").cast<double>();
    p.blend_rate_rad_s = o.attr("blend_rate_rad_s").cast<double>();
    p.rate_sigma_rad_s = o.attr("rate_sigma_rad_s").cast<double>();
    p.rate_max_dt_s = o.attr("rate_max_dt_s").cast<double>();
    p.max_turn_rate_rad_s = o.attr("max_turn_rate_rad_s").cast<double>();
    p.reinit_after_s = o.attr("reinit_after_s").cast<double>();
    const py::object pri = o.attr("priority");
    if (!(PyTuple_Check(pri.ptr()) || PyList_Check(pri.ptr())))
        throw std::invalid_argument("ArbitrationParams.priority must be a tuple or list (the reference runs it)");
    for (const py::handle& h : pri) {
        std::string s;
        p.priority.push_back(as_str(h.ptr(), s) ? s : std::string("\xff"));  // no str equals it
    }
    return p;
}

// the reference's ArbitrationState as it stands; false: not one the step takes
bool state_from(PyObject* o, State& s) {
    static PyObject* const k_time = key("time_s");
    static PyObject* const k_fused = key("fused_rad");
    static PyObject* const k_var = key("fused_var_rad2");
    static PyObject* const k_offset = key("offset_rad");
    static PyObject* const k_sources = key("sources");
    static PyObject* const k_gated = key("gated_since_s");
    static PyObject* const k_last = key("last_fused_s");
    py::object t = attr(o, k_time), f = attr(o, k_fused), v = attr(o, k_var), off = attr(o, k_offset),
               src = attr(o, k_sources), g = attr(o, k_gated), last = attr(o, k_last);
    if (!t || !f || !v || !off || !src || !g || !last) return false;
    if (!as_opt(t.ptr(), s.has_time, s.time_s) || !as_opt(f.ptr(), s.has_fused, s.fused_rad) ||
        !as_num(v.ptr(), s.fused_var_rad2) || !as_num(off.ptr(), s.offset_rad) ||
        !as_opt(g.ptr(), s.has_gated_since, s.gated_since_s))
        return false;
    if (!PyTuple_Check(src.ptr())) return false;  // names != sources compares tuples
    const Py_ssize_t n = PyTuple_GET_SIZE(src.ptr());
    s.sources.resize(static_cast<std::size_t>(n));
    for (Py_ssize_t i = 0; i < n; ++i)
        if (!as_str(PyTuple_GET_ITEM(src.ptr(), i), s.sources[static_cast<std::size_t>(i)])) return false;
    PyObject* l = last.ptr();
    if (!(PyTuple_Check(l) || PyList_Check(l))) return false;
    const Py_ssize_t m = PySequence_Fast_GET_SIZE(l);
    s.last_fused_s.resize(static_cast<std::size_t>(m));
    for (Py_ssize_t i = 0; i < m; ++i) {
        PyObject* pr = PySequence_Fast_GET_ITEM(l, i);
        if (!(PyTuple_Check(pr) || PyList_Check(pr)) || PySequence_Fast_GET_SIZE(pr) != 2) return false;
        auto& kv = s.last_fused_s[static_cast<std::size_t>(i)];
        if (!as_str(PySequence_Fast_GET_ITEM(pr, 0), kv.first) || !as_num(PySequence_Fast_GET_ITEM(pr, 1), kv.second))
            return false;
    }
    return true;
}

// one group name: its bit among the call's distinct groups (false: more than 64)
bool group_bit(const std::string& g, std::vector<std::string>& table, std::uint64_t& bits) {
    std::size_t i = 0;
    while (i < table.size() && table[i] != g) ++i;
    if (i == table.size()) {
        if (i == 64) return false;
        table.push_back(g);
    }
    bits |= std::uint64_t(1) << i;
    return true;
}

// what an aiding record takes from a reading as it stands (the reference passes these objects on)
struct ReadingObjects {
    py::object name, heading, sigma, time, s_innov, s_var, s_ratio;
    std::vector<std::string> groups;  // r.groups: the group names in order, the empty ones left out
};

// the SourceReadings as they stand; false: not ones the step takes
bool readings_from(PyObject* seq, std::vector<Reading>& rs, std::vector<ReadingObjects>& objs) {
    static PyObject* const k_name = key("name");
    static PyObject* const k_heading = key("heading_rad");
    static PyObject* const k_sigma = key("sigma_rad");
    static PyObject* const k_valid = key("valid");
    static PyObject* const k_time = key("time_s");
    static PyObject* const k_group = key("group");
    static PyObject* const k_consistent = key("consistent");
    static PyObject* const k_s_innov = key("source_innovation_rad");
    static PyObject* const k_s_var = key("source_innovation_variance_rad2");
    static PyObject* const k_s_ratio = key("source_test_ratio");
    if (!(PyList_Check(seq) || PyTuple_Check(seq))) return false;
    const Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    rs.resize(static_cast<std::size_t>(n));
    objs.resize(static_cast<std::size_t>(n));
    std::vector<std::string> groups;
    std::string g;
    for (Py_ssize_t i = 0; i < n; ++i) {
        PyObject* o = PySequence_Fast_GET_ITEM(seq, i);
        Reading& r = rs[static_cast<std::size_t>(i)];
        py::object name = attr(o, k_name), h = attr(o, k_heading), s = attr(o, k_sigma), v = attr(o, k_valid),
                   t = attr(o, k_time), gr = attr(o, k_group), c = attr(o, k_consistent);
        if (!name || !h || !s || !v || !t || !gr || !c) return false;
        ReadingObjects& ob = objs[static_cast<std::size_t>(i)];
        ob.s_innov = attr(o, k_s_innov);
        ob.s_var = attr(o, k_s_var);
        ob.s_ratio = attr(o, k_s_ratio);
        if (!ob.s_innov || !ob.s_var || !ob.s_ratio) return false;
        ob.name = name;
        ob.heading = h;
        ob.sigma = s;
        ob.time = t;
        ob.groups.clear();
        if (!as_str(name.ptr(), r.name) || !as_num(h.ptr(), r.heading_rad) || !as_num(s.ptr(), r.sigma_rad) ||
            !as_num(t.ptr(), r.time_s) || !as_truth(v.ptr(), r.valid) || !as_truth(c.ptr(), r.consistent))
            return false;
        for (Py_ssize_t j = 0; j < i; ++j)
            if (rs[static_cast<std::size_t>(j)].name == r.name) return false;  // one record per name
        r.groups = 0;
        PyObject* go = gr.ptr();
        if (PyUnicode_Check(go)) {
            if (!as_str(go, g)) return false;
            if (!g.empty()) {
                if (!group_bit(g, groups, r.groups)) return false;
                ob.groups.push_back(g);
            }
        } else if (PyTuple_Check(go)) {
            for (Py_ssize_t j = 0; j < PyTuple_GET_SIZE(go); ++j) {
                if (!as_str(PyTuple_GET_ITEM(go, j), g)) return false;
                if (!g.empty()) {
                    if (!group_bit(g, groups, r.groups)) return false;
                    ob.groups.push_back(g);
                }
            }
        } else {
            return false;
        }
    }
    return true;
}

// Python's format(x, spec) of a float for a printf spec of fixed digits: printf's digits (correctly
// rounded, as Python's), Python's words for the non-finite ("nan" whatever its sign bit, "inf")
std::string fmt(const char* spec, double x) {
    if (std::isnan(x)) return "nan";
    if (std::isinf(x)) return x > 0 ? "inf" : "-inf";
    const int n = std::snprintf(nullptr, 0, spec, x);
    std::string out(static_cast<std::size_t>(n) + 1, '\0');
    std::snprintf(&out[0], out.size(), spec, x);
    out.resize(static_cast<std::size_t>(n));
    return out;
}

constexpr double RAD_TO_DEG = 180.0 / PI;  // math.degrees: x * (180 / pi)

// (code, detail) of a reading not fused whose words are the core's (the reference's _records); false:
// its code is the caller's (not valid, inconsistent) or there is none: worded by the Python face
bool worded(const Per& v, const Reading& r, const ReadingObjects& ob, double time_s, py::object& code,
            py::object& detail) {
    static const py::str c_gated("gated_out"), c_corr("correlated"), c_nonfinite("non_finite"),
        c_sigma("sigma_out_of_range"), c_stale("stale"), d_nonfinite("non-finite");
    switch (v.why) {
        case GATED_OUT:
            code = c_gated;
            detail = py::str("gated out (NIS " + fmt("%.1f", v.nis) + ")");
            return true;
        case CORRELATED: {
            std::string g;
            for (std::size_t k = 0; k < ob.groups.size(); ++k) g += (k ? "+" : "") + ob.groups[k];
            code = c_corr;
            detail = py::str("correlated with a better source (group " + g + ")");
            return true;
        }
        case NON_FINITE:
            code = c_nonfinite;
            detail = d_nonfinite;
            return true;
        case SIGMA_RANGE:
            code = c_sigma;
            detail = py::str("sigma " + fmt("%.1f", r.sigma_rad * RAD_TO_DEG) + " deg out of range");
            return true;
        case STALE:
            code = c_stale;
            detail = py::str("stale (" + fmt("%.2f", time_s - r.time_s) + " s)");
            return true;
        default:
            return false;
    }
}

py::tuple str_tuple(const std::vector<std::string>& v) {
    py::tuple t(v.size());
    for (std::size_t i = 0; i < v.size(); ++i) t[i] = py::str(v[i]);
    return t;
}

using azimuthd::bind::opt;

// dict(last_fused_s).get(name, nan)
double last_fused(const State& s, const std::string& name) {
    for (auto it = s.last_fused_s.rbegin(); it != s.last_fused_s.rend(); ++it)
        if (it->first == name) return it->second;
    return NAN;
}

}  // namespace

void bind_arbitration(py::module_& m) {
    py::class_<Params>(m, "ArbitrationParams")
        .def(py::init([](const py::object& p) { return params_from(p); }), py::arg("params"),
             "service.heading_arbitration.ArbitrationParams, converted once.");

    m.def(
        "arbitrate",
        [](const Params& p, const py::handle& state, const py::handle& readings, const py::object& time,
           const py::handle& rate, const py::handle& not_offered, const py::handle& record_type) -> py::object {
            static PyObject* const k_source = key("source");
            State st;
            std::vector<Reading> rs;
            std::vector<ReadingObjects> objs;
            bool has_rate = !rate.is_none();
            double r = 0.0;
            if (!PyFloat_Check(time.ptr()) || !PyType_Check(record_type.ptr()) ||
                !PyType_IsSubtype(reinterpret_cast<PyTypeObject*>(record_type.ptr()), &PyTuple_Type))
                return py::none();
            const double time_s = PyFloat_AS_DOUBLE(time.ptr());
            if (!state_from(state.ptr(), st) || !readings_from(readings.ptr(), rs, objs) ||
                (has_rate && !as_num(rate.ptr(), r)))
                return py::none();
            PyObject* no = not_offered.ptr();
            if (!(PyList_Check(no) || PyTuple_Check(no))) return py::none();
            const Py_ssize_t n_no = PySequence_Fast_GET_SIZE(no);
            std::vector<std::string> no_names(static_cast<std::size_t>(n_no));
            for (Py_ssize_t i = 0; i < n_no; ++i) {
                py::object src = attr(PySequence_Fast_GET_ITEM(no, i), k_source);
                if (!src || !as_str(src.ptr(), no_names[static_cast<std::size_t>(i)])) return py::none();
            }
            State next;
            Output out;
            if (!step(st, rs, time_s, p, has_rate, r, next, out)) return py::none();

            // per reading its AidingRecord (tuple.__new__(record_type, values): the record's own checks
            // hold by construction), or, where the code is the caller's, the numbers for the Python face
            static const py::str empty("");
            py::tuple per(rs.size());
            py::object code, detail;
            for (std::size_t i = 0; i < rs.size(); ++i) {
                const Per& v = out.per[i];
                const double ratio = v.innov_var > 0.0 ? v.innov * v.innov / v.innov_var / p.gate_chi2 : NAN;
                const double last = last_fused(next, rs[i].name);
                const ReadingObjects& ob = objs[i];
                if (v.used || worded(v, rs[i], ob, time_s, code, detail)) {
                    if (v.used) code = detail = empty;
                    py::tuple values = py::make_tuple(ob.name, time, code, detail, v.candidate, v.used, last,
                                                      ob.heading, ob.sigma, v.innov, v.innov_var, ratio, ob.s_innov,
                                                      ob.s_var, ob.s_ratio);
                    py::tuple args = py::make_tuple(values);
                    PyObject* rec = PyTuple_Type.tp_new(reinterpret_cast<PyTypeObject*>(record_type.ptr()),
                                                        args.ptr(), nullptr);
                    if (!rec) throw py::error_already_set();
                    per[i] = py::reinterpret_steal<py::object>(rec);
                } else {
                    per[i] = py::make_tuple(v.candidate, v.used, v.why, v.nis, v.innov, v.innov_var, ratio, last);
                }
            }
            py::tuple no_last(no_names.size());
            for (std::size_t i = 0; i < no_names.size(); ++i) no_last[i] = py::float_(last_fused(next, no_names[i]));
            py::tuple events(out.events.size());
            for (std::size_t i = 0; i < out.events.size(); ++i) {
                const Event& e = out.events[i];
                events[i] = py::make_tuple(e.kind, str_tuple(e.to), e.jump_rad, e.dt_s);
            }
            // the state: sources and last_fused_s None where they are the old state's (the caller
            // hands on the very objects, as the reference does)
            py::object sources = py::none(), last = py::none();
            if (out.kind == FUSED) {
                sources = str_tuple(next.sources);
                py::tuple l(next.last_fused_s.size());
                for (std::size_t i = 0; i < next.last_fused_s.size(); ++i)
                    l[i] = py::make_tuple(py::str(next.last_fused_s[i].first), next.last_fused_s[i].second);
                last = l;
            }
            const py::object heading = out.kind == NO_SOURCE ? py::object(py::none()) : py::object(py::float_(out.heading_rad));
            return py::make_tuple(
                py::make_tuple(opt(next.has_fused, next.fused_rad), next.fused_var_rad2, next.offset_rad, sources,
                               opt(next.has_gated_since, next.gated_since_s), last),
                out.kind, heading, out.sigma_rad, out.kind == FUSED ? py::object(str_tuple(out.names)) : py::object(py::none()),
                out.offset_rad, events, per, no_last);
        },
        py::arg("params"), py::arg("state"), py::arg("readings"), py::arg("time_s"), py::arg("heading_rate_rad_s"),
        py::arg("not_offered"), py::arg("record_type"),
        "One step of service.heading_arbitration.arbitrate (time_s checked finite by the caller): None (a value "
        "the core does not take as it stands: the reference answers it) or ((fused_rad, fused_var_rad2, "
        "offset_rad, sources or None = the old, gated_since_s, last_fused_s or None = the old), kind 0 fused / 1 "
        "coast / 2 none, heading_rad or None, sigma_rad, fused names or None, offset_rad, events ((kind, to, "
        "jump_rad, dt_s), ...), per reading its record_type (service.aiding.AidingRecord) or, where its code is "
        "the caller's (not valid, inconsistent), (candidate, used, why, nis, innovation, its variance, test "
        "ratio, time last fused), per not-offered source its time last fused).");
}
