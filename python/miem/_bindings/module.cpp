// pybind11 bindings for miem._core: conversion and validation only; every loop lives in cpp/.
// Arrays arrive as float32 or float64 with any element-aligned strides and are viewed, not copied.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "miem/miem.hpp"

namespace py = pybind11;

namespace {

template <typename T>
std::ptrdiff_t elem_stride(const py::array& a, int axis, const char* name) {
  const std::ptrdiff_t s = a.strides(axis);
  if (s % static_cast<std::ptrdiff_t>(sizeof(T)) != 0) {
    throw std::invalid_argument(std::string(name) + ": strides must be multiples of the item size");
  }
  return s / static_cast<std::ptrdiff_t>(sizeof(T));
}

template <typename T>
miem::PointsView<T> points_view(const py::array& a, const char* name) {
  if (a.ndim() != 2 || a.shape(1) != 3) {
    throw std::invalid_argument(std::string(name) + ": expected shape (N, 3)");
  }
  return miem::PointsView<T>{static_cast<const T*>(a.data()), a.shape(0),
                             elem_stride<T>(a, 0, name), elem_stride<T>(a, 1, name)};
}

template <typename T>
miem::GridView<T> grid_view(const py::array& a) {
  if (a.ndim() != 3 || a.shape(2) != 3) {
    throw std::invalid_argument("grid: expected shape (H, W, 3)");
  }
  return miem::GridView<T>{static_cast<const T*>(a.data()), a.shape(0), a.shape(1),
                           elem_stride<T>(a, 0, "grid"), elem_stride<T>(a, 1, "grid"),
                           elem_stride<T>(a, 2, "grid")};
}

bool is_f32(const py::array& a) { return a.dtype().is(py::dtype::of<float>()); }
bool is_f64(const py::array& a) { return a.dtype().is(py::dtype::of<double>()); }

void require_float(const py::array& a, const char* name) {
  if (!is_f32(a) && !is_f64(a)) {
    throw std::invalid_argument(std::string(name) + ": dtype must be native float32 or float64");
  }
}

py::array_t<double> vec3(const Eigen::Vector3d& v) {
  py::array_t<double> out(3);
  auto m = out.mutable_unchecked<1>();
  for (int i = 0; i < 3; ++i) m(i) = v(i);
  return out;
}

py::tuple plane_tuple(const miem::Plane& p) {
  return py::make_tuple(vec3(p.normal), p.d, vec3(p.centroid), p.rms, p.n_points,
                        vec3(p.eigenvalues));
}

py::tuple fit_plane(const py::array& points, const std::string& method, int num_threads) {
  require_float(points, "points");
  if (method != "eigen" && method != "lstsq") {
    throw std::invalid_argument("method: must be 'eigen' or 'lstsq'");
  }
  const bool eig = method == "eigen";
  miem::Plane p;
  if (is_f32(points)) {
    const auto v = points_view<float>(points, "points");
    py::gil_scoped_release nogil;
    p = eig ? miem::fit_plane_eigen(v, num_threads) : miem::fit_plane_lstsq(v, num_threads);
  } else {
    const auto v = points_view<double>(points, "points");
    py::gil_scoped_release nogil;
    p = eig ? miem::fit_plane_eigen(v, num_threads) : miem::fit_plane_lstsq(v, num_threads);
  }
  return plane_tuple(p);
}

template <bool kHeights>
py::array_t<double> scan_line(const py::array& line, int step) {
  require_float(line, "line");
  py::array_t<double> out(line.ndim() == 2 ? line.shape(0) : 0);
  double* o = out.mutable_data();
  if (is_f32(line)) {
    const auto v = points_view<float>(line, "line");
    py::gil_scoped_release nogil;
    kHeights ? miem::scan_line_heights(v, step, o) : miem::scan_line_angles(v, step, o);
  } else {
    const auto v = points_view<double>(line, "line");
    py::gil_scoped_release nogil;
    kHeights ? miem::scan_line_heights(v, step, o) : miem::scan_line_angles(v, step, o);
  }
  return out;
}

py::tuple detect_organized(const py::array& grid, double theta0, std::vector<int> scales,
                           int max_gap, double min_step, int max_reach, int min_directions,
                           int max_iterations, int window, int height_mode, int num_threads,
                           bool theta0_auto, double height_abs, double height_k) {
  require_float(grid, "grid");
  if (grid.ndim() != 3 || grid.shape(2) != 3) {
    throw std::invalid_argument("grid: expected shape (H, W, 3)");
  }
  miem::DetectParams p;
  p.theta0_deg = theta0;
  p.scales = std::move(scales);
  p.max_gap = max_gap;
  p.min_step = min_step;
  p.max_reach = max_reach;
  p.min_directions = min_directions;
  p.max_iterations = max_iterations;
  p.window = window;
  if (height_mode != 0 && height_mode != 1) throw std::invalid_argument("height: bad mode");
  p.height_mode = static_cast<miem::HeightMode>(height_mode);
  p.num_threads = num_threads;
  p.theta0_auto = theta0_auto;
  p.height_abs = height_abs;
  p.height_k = height_k;
  miem::OrganizedDetector det(p);  // validates

  const py::ssize_t H = grid.shape(0), W = grid.shape(1);
  py::array_t<std::uint8_t> labels({H, W}), flags({H, W});
  py::array_t<double> angle({H, W}), height({H, W});
  miem::OrganizedOutput out{labels.mutable_data(), flags.mutable_data(), angle.mutable_data(),
                            height.mutable_data()};
  miem::DetectSummary s;
  if (is_f32(grid)) {
    const auto v = grid_view<float>(grid);
    py::gil_scoped_release nogil;
    s = det.run(v, out);
  } else {
    const auto v = grid_view<double>(grid);
    py::gil_scoped_release nogil;
    s = det.run(v, out);
  }
  py::list defects;
  for (const miem::Defect& d : s.defects) {
    py::array_t<std::int64_t> idx(static_cast<py::ssize_t>(d.indices.size()));
    std::copy(d.indices.begin(), d.indices.end(), idx.mutable_data());
    defects.append(py::make_tuple(d.id, idx, vec3(d.centroid), vec3(d.normal), d.peak_height,
                                  d.mean_height, d.extent, miem::to_string(d.kind)));
  }
  py::object plane = s.plane ? py::object(plane_tuple(*s.plane)) : py::object(py::none());
  return py::make_tuple(labels, flags, angle, height, plane, s.iterations, defects,
                        s.theta0_deg);
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "miem C++ core (private; use the miem package)";
  m.attr("__version__") = miem::version();
#ifdef MIEM_HAVE_OPENMP
  m.attr("openmp") = true;
#else
  m.attr("openmp") = false;
#endif
  m.def("fit_plane", &fit_plane, py::arg("points"), py::arg("method"), py::arg("num_threads"));
  m.def("scan_line_angles", &scan_line<false>, py::arg("line"), py::arg("step"));
  m.def("scan_line_heights", &scan_line<true>, py::arg("line"), py::arg("step"));
  m.def("detect_organized", &detect_organized, py::arg("grid"), py::arg("theta0"),
        py::arg("scales"), py::arg("max_gap"), py::arg("min_step"), py::arg("max_reach"),
        py::arg("min_directions"), py::arg("max_iterations"), py::arg("window"),
        py::arg("height_mode"), py::arg("num_threads"), py::arg("theta0_auto") = false,
        py::arg("height_abs") = 0.0, py::arg("height_k") = 0.0);
  void bind_unorganized(py::module_ & m);  // python/miem/_bindings/unorganized.cpp
  bind_unorganized(m);
  void bind_stream(py::module_ & m);  // python/miem/_bindings/stream.cpp
  bind_stream(m);
}
