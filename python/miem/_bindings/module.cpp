// pybind11 bindings for miem._core: conversion and validation only; every loop lives in cpp/.
// Arrays arrive as float32 or float64 with any element-aligned strides and are viewed, not copied.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "common.hpp"
#include "miem/miem.hpp"

namespace py = pybind11;

namespace {

using miem::bindings::defect_list;
using miem::bindings::elem_stride;
using miem::bindings::is_f32;
using miem::bindings::plane_or_none;
using miem::bindings::plane_tuple;
using miem::bindings::require_float;
using miem::bindings::with_grid;
using miem::bindings::with_points;

py::tuple fit_plane(const py::array& points, const std::string& method, int num_threads) {
  require_float(points, "points");
  if (method != "eigen" && method != "lstsq") {
    throw std::invalid_argument("method: must be 'eigen' or 'lstsq'");
  }
  const bool eig = method == "eigen";
  const miem::Plane p = with_points(points, "points", [&](const auto& v) {
    return eig ? miem::fit_plane_eigen(v, num_threads) : miem::fit_plane_lstsq(v, num_threads);
  });
  return plane_tuple(p);
}

// The largest finite magnitude of an array of any shape (miem.largest_finite_magnitude over its
// last two axes, for each index of the others; C-contiguous data as one row), read in place.
template <typename T>
double finite_extent_of(const py::array& a, const char* name) {
  const T* base = static_cast<const T*>(a.data());
  const int nd = static_cast<int>(a.ndim());
  if (a.size() == 0) return 0.0;
  if (nd == 0 || (a.flags() & py::array::c_style)) {
    const std::ptrdiff_t n = a.size();
    py::gil_scoped_release nogil;
    return miem::largest_finite_magnitude(base, 1, n, 0, 1);
  }
  std::vector<std::ptrdiff_t> shape(static_cast<std::size_t>(nd)), st(shape.size());
  for (int k = 0; k < nd; ++k) {
    shape[k] = a.shape(k);
    st[k] = elem_stride<T>(a, k, name);
  }
  // rows x cols blocks over the last two axes (a 1-D array: one row), one per index of the rest
  const std::ptrdiff_t rows = nd > 1 ? shape[nd - 2] : 1, row_st = nd > 1 ? st[nd - 2] : 0;
  std::ptrdiff_t blocks = 1;
  for (int k = 0; k < nd - 2; ++k) blocks *= shape[k];
  double top = 0.0;
  py::gil_scoped_release nogil;
  for (std::ptrdiff_t b = 0; b < blocks; ++b) {
    std::ptrdiff_t off = 0, rest = b;
    for (int k = nd - 3; k >= 0; --k) {
      off += (rest % shape[k]) * st[k];
      rest /= shape[k];
    }
    top = std::max(top, miem::largest_finite_magnitude(base + off, rows, shape[nd - 1], row_st,
                                                       st[nd - 1]));
  }
  return top;
}

double finite_extent(const py::array& a, const std::string& name) {
  require_float(a, name.c_str());
  return is_f32(a) ? finite_extent_of<float>(a, name.c_str())
                   : finite_extent_of<double>(a, name.c_str());
}

template <bool kHeights>
py::array_t<double> scan_line(const py::array& line, int step) {
  require_float(line, "line");
  py::array_t<double> out(line.ndim() == 2 ? line.shape(0) : 0);
  double* o = out.mutable_data();
  with_points(line, "line", [&](const auto& v) {
    kHeights ? miem::scan_line_heights(v, step, o) : miem::scan_line_angles(v, step, o);
  });
  return out;
}

double auto_z_resolution(const py::array& grid) {
  require_float(grid, "grid");
  if (grid.ndim() != 3 || grid.shape(2) != 3) {
    throw std::invalid_argument("grid: expected shape (H, W, 3)");
  }
  return with_grid(grid, [](const auto& v) { return miem::auto_z_resolution(v); });
}

py::tuple detect_organized(const py::array& grid, const miem::DetectParams& p) {
  require_float(grid, "grid");
  if (grid.ndim() != 3 || grid.shape(2) != 3) {
    throw std::invalid_argument("grid: expected shape (H, W, 3)");
  }
  miem::OrganizedDetector det(p);  // validates

  const py::ssize_t H = grid.shape(0), W = grid.shape(1);
  py::array_t<std::uint8_t> labels({H, W}), flags({H, W});
  py::array_t<double> angle({H, W}), height({H, W});
  miem::OrganizedOutput out{labels.mutable_data(), flags.mutable_data(), angle.mutable_data(),
                            height.mutable_data()};
  const miem::DetectSummary s = with_grid(grid, [&](const auto& v) { return det.run(v, out); });
  py::list defects = defect_list(s.defects);
  py::object plane = plane_or_none(s.plane);
  return py::make_tuple(labels, flags, angle, height, plane, s.iterations, defects,
                        s.theta0_deg, s.min_step, s.z_resolution, s.z_noise);
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "miem C++ core (private; use the miem package)";
  m.attr("__version__") = miem::version();
  m.attr("AUTO_THETA0_STRAIGHT") = miem::kAutoTheta0Straight;
#ifdef MIEM_HAVE_OPENMP
  m.attr("openmp") = true;
#else
  m.attr("openmp") = false;
#endif
  m.def("max_threads", &miem::max_threads,
        "The most threads any call uses; larger num_threads requests are clamped to it.");
  m.def("finite_extent", &finite_extent, py::arg("a"), py::arg("name"),
        "The largest magnitude among the finite values of a float32/float64 array (0 if none).");
  m.def(
      "check_range",
      [](double magnitude, const std::string& name, bool lower) {
        miem::check_coordinate_range(magnitude, name.c_str(), lower);
      },
      py::arg("magnitude"), py::arg("name"), py::arg("lower"),
      "ValueError (the core's CoordinateRangeError) when a largest finite magnitude lies outside "
      "SPEC's coordinate range (lower=False: the upper bound only).");
  m.def("fit_plane", &fit_plane, py::arg("points"), py::arg("method"), py::arg("num_threads"));
  m.def("scan_line_angles", &scan_line<false>, py::arg("line"), py::arg("step"));
  m.def("scan_line_heights", &scan_line<true>, py::arg("line"), py::arg("step"));
  m.def("detect_organized", &detect_organized, py::arg("grid"), py::arg("params"));
  m.def("auto_z_resolution", &auto_z_resolution, py::arg("grid"));
  void bind_params(py::module_ & m);  // python/miem/_bindings/params.cpp
  bind_params(m);
  void bind_unorganized(py::module_ & m);  // python/miem/_bindings/unorganized.cpp
  bind_unorganized(m);
  void bind_stream(py::module_ & m);  // python/miem/_bindings/stream.cpp
  bind_stream(m);
  void bind_targets(py::module_ & m);  // python/miem/_bindings/targets.cpp
  bind_targets(m);
  void bind_deviation(py::module_ & m);  // python/miem/_bindings/deviation.cpp
  bind_deviation(m);
}
