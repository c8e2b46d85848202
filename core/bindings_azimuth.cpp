// estimators._core.azimuth_propagate: method A's per-sample propagation (core/azimuth_propagation.hpp).
// The Python face is estimators/core.py azimuth_propagate (estimators/azimuth.py's signature).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <stdexcept>

#include "azimuth_propagation.hpp"

namespace py = pybind11;
using namespace azimuthd;
using ArrayC = py::array_t<double, py::array::c_style | py::array::forcecast>;

namespace {

const double* need(const ArrayC& a, py::ssize_t n, const char* name) {
    if (a.size() != n) throw std::invalid_argument(std::string(name) + ": wrong size");
    return a.data();
}

}  // namespace

void bind_azimuth(py::module_& m) {
    m.def("azimuth_propagate",
          [](const ArrayC& q, bool has_prev, double time_prev_s, const ArrayC& gyro_prev, const ArrayC& G,
             const ArrayC& C, double wx, double wy, double wz, double time_s, double max_dt_s) {
              StrapdownState s{};
              const double* qi = need(q, 4, "q_ref_from_sensor");
              for (int i = 0; i < 4; ++i) s.q_ref_from_sensor[i] = qi[i];
              s.has_prev = has_prev;
              s.time_prev_s = time_prev_s;
              if (has_prev) {
                  const double* gp = need(gyro_prev, 3, "gyro_prev_rad_s");
                  for (int i = 0; i < 3; ++i) s.gyro_prev_rad_s[i] = gp[i];
              }
              ArrayC G_out({py::ssize_t(3), py::ssize_t(12)});
              ArrayC C_out({py::ssize_t(3), py::ssize_t(3)});
              double* g = G_out.mutable_data();
              double* c = C_out.mutable_data();
              const double* gi = need(G, 36, "G_gyro");
              const double* ci = need(C, 9, "C_isf_sf");
              for (int i = 0; i < 36; ++i) g[i] = gi[i];
              for (int i = 0; i < 9; ++i) c[i] = ci[i];
              const double w[3] = {wx, wy, wz};
              double dt = 0.0;
              const int code = static_cast<int>(azimuth_propagate(s, g, c, w, time_s, max_dt_s, dt));
              ArrayC q_out(4);
              for (int i = 0; i < 4; ++i) q_out.mutable_data()[i] = s.q_ref_from_sensor[i];
              return py::make_tuple(code, dt, q_out, G_out, C_out);
          },
          py::arg("q_ref_from_sensor"), py::arg("has_prev"), py::arg("time_prev_s"), py::arg("gyro_prev_rad_s"),
          py::arg("G_gyro"), py::arg("C_isf_sf"), py::arg("wx"), py::arg("wy"), py::arg("wz"), py::arg("time_s"),
          py::arg("max_dt_s"),
          "One bias-corrected rate sample: (strapdown code, dt_s, q after, G after (3, 12), C_ISF<-SF after).");
}
