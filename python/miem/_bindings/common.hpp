// Conversions shared by the binding sources: dtype and stride checks, views of NumPy arrays
// over caller memory, and the tuples the Python layer turns into Plane / Defect objects.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <algorithm>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "miem/organized.hpp"
#include "miem/plane.hpp"
#include "miem/views.hpp"

namespace miem::bindings {

namespace py = pybind11;

/// True when the array holds native-order T (any dtype object NumPy deems equivalent, e.g. '=f8').
template <typename T>
bool is_dtype(const py::array& a) {
  return py::isinstance<py::array_t<T>>(a);
}
inline bool is_f32(const py::array& a) { return is_dtype<float>(a); }
inline bool is_f64(const py::array& a) { return is_dtype<double>(a); }

/// Throws unless the data pointer is aligned for T (the Python layer copies arrays that are not,
/// so the core never performs a misaligned load).
template <typename T>
void require_aligned(const py::array& a, const char* name) {
  if (reinterpret_cast<std::uintptr_t>(a.data()) % alignof(T) != 0) {
    throw std::invalid_argument(std::string(name) + ": data is not aligned to its item size");
  }
}

/// Throws unless the array is native float32 or float64 with aligned data.
inline void require_float(const py::array& a, const char* name) {
  if (is_f32(a)) {
    require_aligned<float>(a, name);
  } else if (is_f64(a)) {
    require_aligned<double>(a, name);
  } else {
    throw std::invalid_argument(std::string(name) + ": dtype must be native float32 or float64");
  }
}

/// Stride of an axis in elements of T (the Python layer copies arrays whose strides are not).
template <typename T>
std::ptrdiff_t elem_stride(const py::array& a, int axis, const char* name) {
  const std::ptrdiff_t s = a.strides(axis);
  if (s % static_cast<std::ptrdiff_t>(sizeof(T)) != 0) {
    throw std::invalid_argument(std::string(name) + ": strides must be multiples of the item size");
  }
  return s / static_cast<std::ptrdiff_t>(sizeof(T));
}

/// An (N, 3) array as a PointsView, no copy.
template <typename T>
miem::PointsView<T> points_view(const py::array& a, const char* name) {
  if (a.ndim() != 2 || a.shape(1) != 3) {
    throw std::invalid_argument(std::string(name) + ": expected shape (N, 3)");
  }
  return miem::PointsView<T>{static_cast<const T*>(a.data()), a.shape(0),
                             elem_stride<T>(a, 0, name), elem_stride<T>(a, 1, name)};
}

/// An (H, W, 3) array as a GridView, no copy.
template <typename T>
miem::GridView<T> grid_view(const py::array& a) {
  if (a.ndim() != 3 || a.shape(2) != 3) {
    throw std::invalid_argument("grid: expected shape (H, W, 3)");
  }
  return miem::GridView<T>{static_cast<const T*>(a.data()), a.shape(0), a.shape(1),
                           elem_stride<T>(a, 0, "grid"), elem_stride<T>(a, 1, "grid"),
                           elem_stride<T>(a, 2, "grid")};
}

/// The bindings' one float32/float64 dispatch: checks the dtype, views the (N, 3) array `a` in
/// place as a PointsView<float> or PointsView<double> and calls fn(view) with the GIL released.
template <typename Fn>
auto with_points(const py::array& a, const char* name, Fn&& fn) {
  require_float(a, name);
  if (is_f32(a)) {
    const auto v = points_view<float>(a, name);
    py::gil_scoped_release nogil;
    return fn(v);
  }
  const auto v = points_view<double>(a, name);
  py::gil_scoped_release nogil;
  return fn(v);
}

/// The same for an (H, W, 3) grid (GridView).
template <typename Fn>
auto with_grid(const py::array& a, Fn&& fn) {
  require_float(a, "grid");
  if (is_f32(a)) {
    const auto v = grid_view<float>(a);
    py::gil_scoped_release nogil;
    return fn(v);
  }
  const auto v = grid_view<double>(a);
  py::gil_scoped_release nogil;
  return fn(v);
}

inline py::array_t<double> vec3(const Eigen::Vector3d& v) {
  py::array_t<double> out(3);
  auto m = out.mutable_unchecked<1>();
  for (int i = 0; i < 3; ++i) m(i) = v(i);
  return out;
}

inline py::array_t<std::int64_t> to_array(const std::vector<std::int64_t>& v) {
  py::array_t<std::int64_t> out(static_cast<py::ssize_t>(v.size()));
  std::copy(v.begin(), v.end(), out.mutable_data());
  return out;
}

/// (normal, d, centroid, rms, n_points, eigenvalues)
inline py::tuple plane_tuple(const miem::Plane& p) {
  return py::make_tuple(vec3(p.normal), p.d, vec3(p.centroid), p.rms, p.n_points,
                        vec3(p.eigenvalues));
}

/// The plane tuple, or None.
inline py::object plane_or_none(const std::optional<miem::Plane>& p) {
  return p ? py::object(plane_tuple(*p)) : py::object(py::none());
}

/// [(id, indices, centroid, normal, peak_height, mean_height, extent, kind), ...]
inline py::list defect_list(const std::vector<miem::Defect>& defects) {
  py::list out;
  for (const miem::Defect& d : defects) {
    out.append(py::make_tuple(d.id, to_array(d.indices), vec3(d.centroid), vec3(d.normal),
                              d.peak_height, d.mean_height, d.extent, miem::to_string(d.kind)));
  }
  return out;
}

}  // namespace miem::bindings
