// pybind11 bindings for unorganized clouds: NeighborGrid, estimate_normals, point_spacing and
// detect_points. Conversion and validation only; arrays are viewed in place (float32 / float64,
// element-aligned strides) and the GIL is released around every computation.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "common.hpp"
#include "miem/neighbor_grid.hpp"
#include "miem/unorganized.hpp"

namespace py = pybind11;

namespace {

using miem::bindings::defect_list;
using miem::bindings::plane_or_none;
using miem::bindings::require_float;
using miem::bindings::to_array;
using miem::bindings::with_points;

void require_points(const py::array& a, const char* name) {
  require_float(a, name);
  if (a.ndim() != 2 || a.shape(1) != 3) {
    throw std::invalid_argument(std::string(name) + ": expected shape (N, 3)");
  }
}

// A grid over a float32 or float64 array that it keeps alive.
class PyNeighborGrid {
 public:
  PyNeighborGrid(py::array points, double cell_size, int num_threads) : points_(points) {
    with_points(points_, "points", [&](const auto& v) {
      using T = std::remove_const_t<std::remove_pointer_t<decltype(v.data)>>;
      auto g = std::make_unique<miem::NeighborGrid<T>>(v, cell_size, num_threads);
      if constexpr (std::is_same_v<T, float>) {
        f32_ = std::move(g);
      } else {
        f64_ = std::move(g);
      }
    });
  }

  template <typename Fn>
  auto with(Fn&& fn) const {
    return f32_ ? fn(*f32_) : fn(*f64_);
  }

  py::array_t<std::int64_t> query_index(std::int64_t index, double r) const {
    std::vector<std::int64_t> out;
    {
      py::gil_scoped_release nogil;
      with([&](const auto& g) {
        g.radius_query(static_cast<std::ptrdiff_t>(index), r, out);
        return 0;
      });
    }
    return to_array(out);
  }

  py::array_t<std::int64_t> query_point(double x, double y, double z, double r) const {
    std::vector<std::int64_t> out;
    {
      py::gil_scoped_release nogil;
      with([&](const auto& g) {
        g.radius_query(Eigen::Vector3d(x, y, z), r, out);
        return 0;
      });
    }
    return to_array(out);
  }

  py::array_t<double> nearest_distances(int num_threads) const {
    py::array_t<double> out(points_.shape(0));
    double* o = out.mutable_data();
    {
      py::gil_scoped_release nogil;
      with([&](const auto& g) {
        g.nearest_distances(o, num_threads);
        return 0;
      });
    }
    return out;
  }

  double cell_size() const {
    return with([](const auto& g) { return g.cell_size(); });
  }
  std::ptrdiff_t num_cells() const {
    return with([](const auto& g) { return g.num_cells(); });
  }
  std::ptrdiff_t num_indexed() const {
    return with([](const auto& g) { return g.num_indexed(); });
  }
  py::array points() const { return points_; }

 private:
  py::array points_;  // keeps the viewed memory alive
  std::unique_ptr<miem::NeighborGrid<float>> f32_;
  std::unique_ptr<miem::NeighborGrid<double>> f64_;
};

double point_spacing(const py::array& points, int num_threads) {
  return with_points(points, "points",
                     [&](const auto& v) { return miem::point_spacing(v, num_threads); });
}

py::array_t<double> distinct_spacings(const py::array& points, double merge_distance,
                                      int num_threads) {
  require_points(points, "points");
  py::array_t<double> out(points.shape(0));
  double* o = out.mutable_data();
  with_points(points, "points", [&](const auto& v) {
    miem::distinct_spacings(v, merge_distance, o, num_threads);
  });
  return out;
}

py::tuple estimate_normals(const py::array& points, double radius, int num_threads) {
  require_points(points, "points");
  const py::ssize_t n = points.shape(0);
  py::array_t<double> normals({n, static_cast<py::ssize_t>(3)}), rms(n);
  py::array_t<std::int64_t> count(n);
  py::array_t<bool> valid(n);
  const miem::NormalsOutput out{normals.mutable_data(), rms.mutable_data(), count.mutable_data(),
                                reinterpret_cast<std::uint8_t*>(valid.mutable_data())};
  with_points(points, "points",
              [&](const auto& v) { miem::estimate_normals(v, radius, out, num_threads); });
  return py::make_tuple(normals, rms, count, valid);
}

// edge_rms_median: miem::PointsDetectHooks::edge_rms_median (internal, miem.dask).
py::tuple detect_points(const py::array& points, const miem::PointsDetectParams& p,
                        double edge_rms_median) {
  require_points(points, "points");
  miem::validate(p);
  miem::PointsDetectHooks hooks;
  hooks.edge_rms_median = edge_rms_median;

  const py::ssize_t n = points.shape(0);
  py::array_t<std::uint8_t> labels(n), flags(n);
  py::array_t<double> angle(n), height(n);
  py::array_t<bool> degenerate(n);
  const miem::PointsOutput out{labels.mutable_data(), flags.mutable_data(), angle.mutable_data(),
                               height.mutable_data(),
                               reinterpret_cast<std::uint8_t*>(degenerate.mutable_data())};
  const miem::PointsDetectSummary s = with_points(
      points, "points", [&](const auto& v) { return miem::detect_points(v, p, out, hooks); });
  py::list defects = defect_list(s.defects);
  py::object plane = plane_or_none(s.plane);
  py::list stages;
  for (const auto& st : s.stage_seconds) stages.append(py::make_tuple(st.name, st.wall, st.cpu));
  return py::make_tuple(labels, flags, angle, height, degenerate, plane, s.iterations, defects,
                        s.spacing, s.radius, s.min_step, s.link, s.height_radius, s.merged,
                        stages, s.edge_radius);
}

// miem::edge_rms_survey (internal, miem.dask).
py::array_t<double> edge_rms_survey(const py::array& points, const miem::PointsDetectParams& p) {
  require_points(points, "points");
  miem::validate(p);
  const py::ssize_t n = points.shape(0);
  py::array_t<double> rms(n);
  double* o = rms.mutable_data();
  with_points(points, "points", [&](const auto& v) { miem::edge_rms_survey(v, p, o); });
  return rms;
}

}  // namespace

void bind_unorganized(py::module_& m) {
  py::class_<PyNeighborGrid>(m, "NeighborGrid")
      .def(py::init<py::array, double, int>(), py::arg("points"), py::arg("cell_size"),
           py::arg("num_threads") = 0)
      .def("query_index", &PyNeighborGrid::query_index, py::arg("index"), py::arg("r"))
      .def("query_point", &PyNeighborGrid::query_point, py::arg("x"), py::arg("y"), py::arg("z"),
           py::arg("r"))
      .def("nearest_distances", &PyNeighborGrid::nearest_distances, py::arg("num_threads") = 0)
      .def_property_readonly("cell_size", &PyNeighborGrid::cell_size)
      .def_property_readonly("num_cells", &PyNeighborGrid::num_cells)
      .def_property_readonly("num_indexed", &PyNeighborGrid::num_indexed)
      .def_property_readonly("points", &PyNeighborGrid::points);
  m.def("point_spacing", &point_spacing, py::arg("points"), py::arg("num_threads"));
  m.def("distinct_spacings", &distinct_spacings, py::arg("points"), py::arg("merge_distance"),
        py::arg("num_threads"));
  m.def("estimate_normals", &estimate_normals, py::arg("points"), py::arg("radius"),
        py::arg("num_threads"));
  m.def("detect_points", &detect_points, py::arg("points"), py::arg("params"),
        py::arg("edge_rms_median") = std::numeric_limits<double>::quiet_NaN());
  m.def("edge_rms_survey", &edge_rms_survey, py::arg("points"), py::arg("params"));
}
