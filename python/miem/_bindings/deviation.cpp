// pybind11 bindings for the deviation from a reference surface: ReferenceSurface and
// label_deviation. Conversion and validation only; the GIL is released around every computation.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "common.hpp"
#include "miem/deviation.hpp"

namespace py = pybind11;

namespace {

using miem::bindings::defect_list;
using miem::bindings::points_view;
using miem::bindings::require_float;
using miem::bindings::with_points;

using F64 = py::array_t<double, py::array::c_style | py::array::forcecast>;

void require_rows(const py::array& a, py::ssize_t n, const char* name) {
  if (a.ndim() != 2 || a.shape(0) != n || a.shape(1) != 3) {
    throw std::invalid_argument(std::string(name) + ": expected shape (" + std::to_string(n) +
                                ", 3)");
  }
}

class PyReferenceSurface {
 public:
  PyReferenceSurface(const py::array& points, const F64& normals, double cell_size,
                     int num_threads) {
    if (!points.dtype().is(py::dtype::of<double>())) {
      throw std::invalid_argument("reference: dtype must be float64");
    }
    const auto v = points_view<double>(points, "reference");
    require_rows(normals, points.shape(0), "normals");
    const double* n = normals.data();
    py::gil_scoped_release nogil;
    surface_ = std::make_unique<miem::ReferenceSurface>(v, n, cell_size, num_threads);
  }

  // (deviation, distance, nearest, covered)
  py::tuple deviation(const py::array& scan, double max_distance, double max_lateral,
                      int num_threads) const {
    require_float(scan, "scan");
    const py::ssize_t n = scan.ndim() == 2 ? scan.shape(0) : 0;
    py::array_t<double> dev(n), dist(n);
    py::array_t<std::int64_t> nearest(n);
    py::array_t<bool> covered(n);
    const miem::DeviationOutput out{dev.mutable_data(), dist.mutable_data(),
                                    nearest.mutable_data(),
                                    reinterpret_cast<std::uint8_t*>(covered.mutable_data())};
    with_points(scan, "scan", [&](const auto& v) {
      surface_->deviation(v, max_distance, max_lateral, out, num_threads);
    });
    return py::make_tuple(dev, dist, nearest, covered);
  }

  std::ptrdiff_t size() const { return surface_->size(); }
  double cell_size() const { return surface_->cell_size(); }

 private:
  std::unique_ptr<miem::ReferenceSurface> surface_;
};

// (labels, defects)
py::tuple label_deviation(const py::array& points, const F64& deviation,
                          const py::array_t<bool, py::array::c_style | py::array::forcecast>& covered,
                          const py::object& normals, double tolerance, double dont_care,
                          double link) {
  require_float(points, "points");
  if (points.ndim() != 2 || points.shape(1) != 3) {
    throw std::invalid_argument("points: expected shape (N, 3)");
  }
  const py::ssize_t n = points.shape(0);
  if (deviation.ndim() != 1 || deviation.shape(0) != n) {
    throw std::invalid_argument("deviation: expected shape (" + std::to_string(n) + ",)");
  }
  if (covered.ndim() != 1 || covered.shape(0) != n) {
    throw std::invalid_argument("covered: expected shape (" + std::to_string(n) + ",)");
  }
  F64 nrm;
  const double* np = nullptr;
  if (!normals.is_none()) {
    nrm = F64::ensure(normals);
    if (!nrm) throw std::invalid_argument("normals: expected a float array");
    require_rows(nrm, n, "normals");
    np = nrm.data();
  }
  const miem::DeviationLabelParams params{tolerance, dont_care, link};
  py::array_t<std::uint8_t> labels(n);
  std::uint8_t* lp = labels.mutable_data();
  const double* dp = deviation.data();
  const auto* cp = reinterpret_cast<const std::uint8_t*>(covered.data());
  const std::vector<miem::Defect> defects = with_points(points, "points", [&](const auto& v) {
    return miem::label_deviation(v, dp, cp, np, params, lp);
  });
  return py::make_tuple(labels, defect_list(defects));
}

}  // namespace

void bind_deviation(py::module_& m) {
  py::class_<PyReferenceSurface>(m, "ReferenceSurface")
      .def(py::init<const py::array&, const F64&, double, int>(), py::arg("points"),
           py::arg("normals"), py::arg("cell_size"), py::arg("num_threads") = 0)
      .def("deviation", &PyReferenceSurface::deviation, py::arg("scan"), py::arg("max_distance"),
           py::arg("max_lateral"), py::arg("num_threads") = 0)
      .def_property_readonly("size", &PyReferenceSurface::size)
      .def_property_readonly("cell_size", &PyReferenceSurface::cell_size);
  m.def("label_deviation", &label_deviation, py::arg("points"), py::arg("deviation"),
        py::arg("covered"), py::arg("normals"), py::arg("tolerance"), py::arg("dont_care"),
        py::arg("link"));
}
