// estimators._core: the link's per-datagram scan (core/mavlink_frames.hpp; the reference and the Python
// face are mavlink_io/frame_scan.py). split_raw_imu(frame_type, data) -> [bytes | frame_type(...)]: the
// bytes for pymavlink and the unsigned CRC-checked RAW_IMU frames, in order, as frame_scan.split_raw_imu
// gives them; frame_type is frame_scan.RawImuFrame (a NamedTuple: built as tuple.__new__ builds it).
#include <pybind11/pybind11.h>

#include <cstdint>

#include "mavlink_frames.hpp"

namespace py = pybind11;

namespace {

py::object steal(PyObject* o) {
    if (o == nullptr) throw py::error_already_set();
    return py::reinterpret_steal<py::object>(o);
}

// RAW_IMU's time_usec (payload bytes 0-7, little endian) and id (byte 26); a payload cut by MAVLink 2's
// trailing-zero truncation reads its missing bytes as zeros.
std::uint64_t time_usec_of(const std::uint8_t* p, std::size_t len) {
    std::uint64_t t = 0;
    for (std::size_t i = 0; i < 8 && i < len; ++i) t |= static_cast<std::uint64_t>(p[i]) << (8 * i);
    return t;
}

py::list split_raw_imu(py::handle frame_type, py::handle data) {
    py::object bytes_obj = PyBytes_CheckExact(data.ptr()) ? py::reinterpret_borrow<py::object>(data)
                                                          : steal(PyBytes_FromObject(data.ptr()));
    const char* raw = PyBytes_AS_STRING(bytes_obj.ptr());
    const auto* d = reinterpret_cast<const std::uint8_t*>(raw);
    const std::size_t n = static_cast<std::size_t>(PyBytes_GET_SIZE(bytes_obj.ptr()));
    if (!PyType_Check(frame_type.ptr()) || !PyType_IsSubtype(reinterpret_cast<PyTypeObject*>(frame_type.ptr()),
                                                             &PyTuple_Type))
        throw py::type_error("frame_type must be a tuple subclass (frame_scan.RawImuFrame)");
    auto* ft = reinterpret_cast<PyTypeObject*>(frame_type.ptr());
    py::list out;
    auto append = [&out](py::object o) {
        if (PyList_Append(out.ptr(), o.ptr()) != 0) throw py::error_already_set();
    };
    azimuthd::mavlink::split_raw_imu(
        d, n,
        [&](std::size_t from, std::size_t to) {
            if (from == 0 && to == n) append(bytes_obj);  // the whole read: the object itself, as data[0:]
            else append(steal(PyBytes_FromStringAndSize(raw + from, static_cast<Py_ssize_t>(to - from))));
        },
        [&](const azimuthd::mavlink::RawImuSpan& s) {
            const std::uint8_t* p = d + s.payload_at;
            py::object fields = steal(PyTuple_Pack(
                6, steal(PyLong_FromLong(s.src_system)).ptr(), steal(PyLong_FromLong(s.src_component)).ptr(),
                steal(PyLong_FromLong(s.seq)).ptr(),
                steal(PyBytes_FromStringAndSize(raw + s.payload_at, static_cast<Py_ssize_t>(s.payload_len))).ptr(),
                steal(PyLong_FromUnsignedLongLong(time_usec_of(p, s.payload_len))).ptr(),
                steal(PyLong_FromLong(s.payload_len > 26 ? p[26] : 0)).ptr()));
            py::object args = steal(PyTuple_Pack(1, fields.ptr()));
            append(steal(PyTuple_Type.tp_new(ft, args.ptr(), nullptr)));  // tuple.__new__(RawImuFrame, fields)
        });
    return out;
}

}  // namespace

void bind_link(py::module_& m) {
    m.def("split_raw_imu", &split_raw_imu, py::arg("frame_type"), py::arg("data"),
          "mavlink_io.frame_scan.split_raw_imu in C++: a read as byte segments for pymavlink and frame_type "
          "(RawImuFrame) tuples for its unsigned CRC-checked RAW_IMU frames, in order");
}
