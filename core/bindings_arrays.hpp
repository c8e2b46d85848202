// Fixed-size arrays and optional floats between Python and C++ for the binding files (one copy for all of them).
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <array>
#include <cstddef>
#include <stdexcept>
#include <string>

namespace azimuthd {
namespace bind {

namespace py = pybind11;

// N doubles from anything numpy turns into a C-contiguous float64 array; ``name`` says which in the error
template <std::size_t N>
std::array<double, N> arr(const py::handle& o, const char* name = "array") {
    auto a = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(o);
    if (!a || static_cast<std::size_t>(a.size()) != N)
        throw std::invalid_argument(std::string(name) + ": " + std::to_string(N) + " values expected");
    std::array<double, N> out{};
    for (std::size_t i = 0; i < N; ++i) out[i] = a.data()[i];
    return out;
}

// a 1-D float64 numpy array of N values
template <std::size_t N>
py::array_t<double> np1(const std::array<double, N>& x) {
    py::array_t<double> a(static_cast<py::ssize_t>(N));
    double* o = a.mutable_data();
    for (std::size_t i = 0; i < N; ++i) o[i] = x[i];
    return a;
}

// a float, or None when the value is absent (the core's has_* flags are Python's Optional)
inline py::object opt(bool has, double v) { return has ? py::object(py::float_(v)) : py::object(py::none()); }

}  // namespace bind
}  // namespace azimuthd
