// estimators._core.solution_numbers: the numbers of the filter step's solution (core/solution.hpp)
// from the held attitude and heading filters in one call; estimators/core.py solution_numbers is
// its Python face and service/pipeline.py Pipeline._solution the reference.
#include <pybind11/pybind11.h>

#include "bindings_arrays.hpp"
#include "solution.hpp"

namespace py = pybind11;
using namespace azimuthd;
using azimuthd::bind::opt;

void bind_solution(py::module_& m) {
    m.def("solution_numbers",
          [](const polar::State& pa, const polar_heading::State& ph, double t, bool has_prev, double prev_t,
             double prev_yaw, double r0, double r1, double r2) -> py::object {
              if (!pa.initialised) return py::none();
              const solution::AttitudeNumbers a =
                  solution::attitude_numbers(pa, t, has_prev, prev_t, prev_yaw, V3{r0, r1, r2});
              py::object c = py::none();
              if (ph.initialised) {
                  double heading = 0.0, var = 0.0;
                  polar_heading::estimate(ph, heading, var);
                  c = py::make_tuple(heading, var, ph.source_available, opt(ph.has_rejected_since, ph.rejected_since_s),
                                     opt(ph.has_last_mag, ph.last_mag_time_s));
              }
              return py::make_tuple(a.roll, a.pitch, a.roll_sigma, a.pitch_sigma, a.yaw_P,
                                    opt(a.has_rate, a.heading_rate), c);
          },
          py::arg("polar_attitude"), py::arg("polar_heading"), py::arg("time_s"), py::arg("has_prev"),
          py::arg("prev_time_s"), py::arg("prev_yaw_P_rad"), py::arg("rate_x"), py::arg("rate_y"), py::arg("rate_z"),
          "None before C's attitude filter levelled, else (roll, pitch, roll sigma, pitch sigma, yaw of q_P_from_body, "
          "heading rate or None, C's heading: None before its first, else (heading, published variance, "
          "source_available, rejected_since_s or None, last_mag_time_s or None)).");
}
