// estimators._core: the Python binding of the compiled core (pybind11). Batch calls take typed
// numpy arrays (N x 3 rates and forces, N times) and loop in C++ with the GIL released; the
// per-sample calls exist for callers that still step one sample at a time. The Python glue is
// estimators/core.py; the Python reference implementations stay in estimators/.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <stdexcept>
#include <string>
#include <utility>

#include "levelling.hpp"
#include "strapdown.hpp"

namespace py = pybind11;
using azimuthd::LevellingAcc;
using azimuthd::StrapdownCode;
using azimuthd::StrapdownState;

using ArrayD = py::array_t<double, py::array::c_style | py::array::forcecast>;

namespace {

const double* vec(const ArrayD& a, py::ssize_t n, const char* name) {
    if (a.ndim() != 1 || a.shape(0) != n)
        throw std::invalid_argument(std::string(name) + " must have shape (" + std::to_string(n) + ",)");
    return a.data();
}

// (N, 3) samples and (N,) times; returns N.
py::ssize_t rows3(const ArrayD& x, const char* name) {
    if (x.ndim() != 2 || x.shape(1) != 3)
        throw std::invalid_argument(std::string(name) + " must have shape (N, 3)");
    return x.shape(0);
}

StrapdownState strapdown_state(const ArrayD& q, bool has_prev, double time_prev_s, const ArrayD& gyro_prev) {
    StrapdownState s{};
    const double* qp = vec(q, 4, "q_ref_from_sensor");
    for (int i = 0; i < 4; ++i) s.q_ref_from_sensor[i] = qp[i];
    s.has_prev = has_prev;
    s.time_prev_s = time_prev_s;
    if (has_prev) {
        const double* gp = vec(gyro_prev, 3, "gyro_prev_rad_s");
        for (int i = 0; i < 3; ++i) s.gyro_prev_rad_s[i] = gp[i];
    }
    return s;
}

ArrayD copy_out(const double* x, py::ssize_t n) {
    ArrayD out(n);
    double* o = out.mutable_data();
    for (py::ssize_t i = 0; i < n; ++i) o[i] = x[i];
    return out;
}

// The levelling accumulator as a flat float64 vector (what estimators/core.py packs from and
// unpacks into estimators.levelling.LevellingState): the field order of LEVELLING_FIELDS below.
constexpr py::ssize_t LEVELLING_PACKED = azimuthd::LEVELLING_PACKED_SIZE;

void pack(const LevellingAcc& s, double* o) { azimuthd::levelling_pack(s, o); }

LevellingAcc unpack(const double* p) { return azimuthd::levelling_unpack(p); }

}  // namespace

void bind_synthetic_ahrs(py::module_& m);  // core/bindings_ahrs.cpp: method B
void bind_checks(py::module_& m);          // core/bindings_checks.cpp: the per-sample checks
void bind_azimuth(py::module_& m);         // core/bindings_azimuth.cpp: method A's propagation
void bind_polar(py::module_& m);           // core/bindings_polar.cpp: method C's attitude filter
void bind_polar_heading(py::module_& m);   // core/bindings_polar_heading.cpp: method C's heading filter
void bind_hot_path(py::module_& m);        // core/bindings_hot_path.cpp: the Pipeline's per-sample hot path
void bind_phases(py::module_& m);          // core/bindings_phases.cpp: the flight phases
void bind_fit(py::module_& m);             // core/bindings_fit.cpp: method A's re-solve, method D's RLS
void bind_arbitration(py::module_& m);     // core/bindings_arbitration.cpp: the heading arbitration
void bind_filter_chain(py::module_& m);    // core/bindings_filter_chain.cpp: C's rest detection, its filter-step chain
void bind_solution(py::module_& m);        // core/bindings_solution.cpp: the filter step's solution numbers
void bind_link(py::module_& m);            // core/bindings_link.cpp: the MAVLink link's per-datagram scan

PYBIND11_MODULE(_core, m) {
    m.doc() = "azimuthd's compiled estimator core (estimators/core.py is its Python face)";
    bind_synthetic_ahrs(m);
    bind_checks(m);
    bind_azimuth(m);
    bind_polar(m);
    bind_polar_heading(m);
    bind_hot_path(m);
    bind_phases(m);
    bind_fit(m);
    bind_arbitration(m);
    bind_filter_chain(m);
    bind_solution(m);
    bind_link(m);

    m.def("strapdown_step",
          [](const ArrayD& q, bool has_prev, double time_prev_s, const ArrayD& gyro_prev, const ArrayD& gyro,
             double time_s, double max_dt_s) {
              StrapdownState s = strapdown_state(q, has_prev, time_prev_s, gyro_prev);
              double dt = 0.0;
              const StrapdownCode code =
                  azimuthd::strapdown_step(s, vec(gyro, 3, "gyro_rad_s"), time_s, max_dt_s, dt);
              return py::make_tuple(static_cast<int>(code), dt, copy_out(s.q_ref_from_sensor, 4));
          },
          py::arg("q_ref_from_sensor"), py::arg("has_prev"), py::arg("time_prev_s"), py::arg("gyro_prev_rad_s"),
          py::arg("gyro_rad_s"), py::arg("time_s"), py::arg("max_dt_s"),
          "One sample: (code, dt_s, q_ref_from_sensor after it). Codes: see StrapdownCode.");

    m.def("strapdown_propagate",
          [](const ArrayD& q, bool has_prev, double time_prev_s, const ArrayD& gyro_prev, const ArrayD& gyro,
             const ArrayD& time, double max_dt_s) {
              const py::ssize_t n = rows3(gyro, "gyro_rad_s");
              const double* t = vec(time, n, "time_s");
              StrapdownState s = strapdown_state(q, has_prev, time_prev_s, gyro_prev);
              py::array_t<double> q_out({n, py::ssize_t(4)});
              py::array_t<std::int8_t> codes(n);
              py::array_t<double> dts(n);
              double* qo = q_out.mutable_data();
              std::int8_t* co = codes.mutable_data();
              double* dto = dts.mutable_data();
              const double* g = gyro.data();
              {
                  py::gil_scoped_release nogil;
                  for (py::ssize_t k = 0; k < n; ++k) {
                      co[k] = static_cast<std::int8_t>(azimuthd::strapdown_step(s, g + 3 * k, t[k], max_dt_s, dto[k]));
                      for (int i = 0; i < 4; ++i) qo[4 * k + i] = s.q_ref_from_sensor[i];
                  }
              }
              return py::make_tuple(q_out, codes, dts, s.has_prev, s.time_prev_s, copy_out(s.gyro_prev_rad_s, 3),
                                    copy_out(s.q_ref_from_sensor, 4));
          },
          py::arg("q_ref_from_sensor"), py::arg("has_prev"), py::arg("time_prev_s"), py::arg("gyro_prev_rad_s"),
          py::arg("gyro_rad_s"), py::arg("time_s"), py::arg("max_dt_s"),
          "N samples: (q after each (N, 4), code (N,), dt_s (N,), has_prev, time_prev_s, gyro_prev_rad_s, q).");

    // The propagation held in the core between samples (the per-sample hot path of the Pipeline:
    // one call, no state objects built per sample).
    py::class_<StrapdownState>(m, "Strapdown")
        .def(py::init([](const ArrayD& q, bool has_prev, double time_prev_s, const ArrayD& gyro_prev) {
                 return strapdown_state(q, has_prev, time_prev_s, gyro_prev);
             }),
             py::arg("q_ref_from_sensor"), py::arg("has_prev"), py::arg("time_prev_s"), py::arg("gyro_prev_rad_s"))
        .def("step",
             [](StrapdownState& s, const ArrayD& gyro, double time_s, double max_dt_s) {
                 double dt = 0.0;
                 const StrapdownCode code = azimuthd::strapdown_step(s, vec(gyro, 3, "gyro_rad_s"), time_s, max_dt_s, dt);
                 return py::make_tuple(static_cast<int>(code), dt);
             },
             py::arg("gyro_rad_s"), py::arg("time_s"), py::arg("max_dt_s"), "One sample: (code, dt_s).")
        .def("step3",
             [](StrapdownState& s, double wx, double wy, double wz, double time_s, double max_dt_s) {
                 // the per-sample hot path: plain floats in (no array conversion), (code, dt_s) out
                 const double w[3] = {wx, wy, wz};
                 double dt = 0.0;
                 const StrapdownCode code = azimuthd::strapdown_step(s, w, time_s, max_dt_s, dt);
                 return std::make_pair(static_cast<int>(code), dt);
             },
             py::arg("wx"), py::arg("wy"), py::arg("wz"), py::arg("time_s"), py::arg("max_dt_s"),
             "One sample as three floats (rad/s): (code, dt_s).")
        .def_property_readonly("q_ref_from_sensor", [](const StrapdownState& s) { return copy_out(s.q_ref_from_sensor, 4); })
        .def_readonly("has_prev", &StrapdownState::has_prev)
        .def_readonly("time_prev_s", &StrapdownState::time_prev_s)
        .def_property_readonly("gyro_prev_rad_s", [](const StrapdownState& s) { return copy_out(s.gyro_prev_rad_s, 3); });

    m.attr("LEVELLING_PACKED") = LEVELLING_PACKED;
    m.def("levelling_accumulate",
          [](const ArrayD& packed, const ArrayD& gyro, const ArrayD& accel, const ArrayD& time, double batch_s) {
              const py::ssize_t n = rows3(gyro, "gyro_rad_s");
              if (rows3(accel, "accel_m_s2") != n) throw std::invalid_argument("gyro and accel differ in length");
              const double* t = vec(time, n, "time_s");
              LevellingAcc s = unpack(vec(packed, LEVELLING_PACKED, "packed"));
              py::array_t<bool> used(n);
              bool* u = used.mutable_data();
              const double* g = gyro.data();
              const double* a = accel.data();
              {
                  py::gil_scoped_release nogil;
                  for (py::ssize_t k = 0; k < n; ++k)
                      u[k] = azimuthd::levelling_step(s, g + 3 * k, a + 3 * k, t[k], batch_s);
              }
              ArrayD out(LEVELLING_PACKED);
              pack(s, out.mutable_data());
              return py::make_tuple(out, used);
          },
          py::arg("packed"), py::arg("gyro_rad_s"), py::arg("accel_m_s2"), py::arg("time_s"), py::arg("batch_s"),
          "N samples into the packed accumulator (time NaN = untimed): (packed after, accepted (N,) bool).");
}
