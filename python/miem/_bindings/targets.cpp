// pybind11 bindings for grinding targets: TargetParams, Target, TargetPlan and plan_targets.
// Conversion and validation only; the geometry lives in cpp/src/targets.cpp.
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "common.hpp"
#include "miem/targets.hpp"

namespace py = pybind11;

namespace {

using miem::bindings::require_float;
using miem::bindings::with_grid;

miem::DefectKind kind_of(const std::string& s) {
  if (s == "protrusion") return miem::DefectKind::kProtrusion;
  if (s == "pit") return miem::DefectKind::kPit;
  if (s == "isolated") return miem::DefectKind::kIsolated;
  throw std::invalid_argument("defects: unknown kind '" + s + "'");
}

// (id, indices, normal, peak_height, kind) tuples, as the Python Defect objects hold them.
std::vector<miem::Defect> to_defects(const py::list& items) {
  std::vector<miem::Defect> out;
  out.reserve(items.size());
  for (const py::handle& h : items) {
    const auto t = h.cast<py::tuple>();
    miem::Defect d;
    d.id = t[0].cast<int>();
    const auto idx = t[1].cast<py::array_t<std::int64_t, py::array::c_style | py::array::forcecast>>();
    d.indices.assign(idx.data(), idx.data() + idx.size());
    d.normal = t[2].cast<Eigen::Vector3d>();
    d.peak_height = t[3].cast<double>();
    d.kind = kind_of(t[4].cast<std::string>());
    out.push_back(std::move(d));
  }
  return out;
}

template <typename A>
const A* flat(const py::array& a, py::ssize_t n, const char* name) {
  if (a.size() != n || !(a.flags() & py::array::c_style)) {
    throw std::invalid_argument(std::string(name) + ": expected a contiguous array of H*W values");
  }
  return static_cast<const A*>(a.data());
}

miem::TargetPlan plan(const py::array& grid, const py::array& labels, const py::array& height,
                      const py::list& defect_items, const py::array& transforms,
                      const miem::TargetParams& params, const py::object& roi_mask) {
  require_float(grid, "grid");
  if (!labels.dtype().is(py::dtype::of<std::uint8_t>())) {
    throw std::invalid_argument("labels: dtype must be uint8");
  }
  if (!height.dtype().is(py::dtype::of<double>())) {
    throw std::invalid_argument("height: dtype must be float64");
  }
  if (!transforms.dtype().is(py::dtype::of<double>()) || !(transforms.flags() & py::array::c_style) ||
      transforms.ndim() != 3 || transforms.shape(1) != 4 || transforms.shape(2) != 4) {
    throw std::invalid_argument("T_base_sensor: expected a contiguous float64 (K, 4, 4) array");
  }
  const py::ssize_t n = grid.ndim() == 3 ? grid.shape(0) * grid.shape(1) : 0;
  const auto* lab = flat<std::uint8_t>(labels, n, "labels");
  const auto* hgt = flat<double>(height, n, "height");
  const std::uint8_t* roi = nullptr;
  py::array roi_arr;
  if (!roi_mask.is_none()) {
    roi_arr = roi_mask.cast<py::array>();
    if (!roi_arr.dtype().is(py::dtype::of<std::uint8_t>())) {
      throw std::invalid_argument("roi: mask dtype must be uint8");
    }
    roi = flat<std::uint8_t>(roi_arr, n, "roi");
  }
  const std::vector<miem::Defect> defects = to_defects(defect_items);
  const miem::TransformsView tv{static_cast<const double*>(transforms.data()), transforms.shape(0)};
  return with_grid(grid, [&](const auto& v) {
    return miem::plan_targets(v, lab, hgt, defects, tv, params, roi);
  });
}

template <int N>
py::array_t<double> stack(const std::vector<miem::Target>& ts,
                          Eigen::Matrix<double, N, 1> (*get)(const miem::Target&)) {
  py::array_t<double> out({static_cast<py::ssize_t>(ts.size()), static_cast<py::ssize_t>(N)});
  auto m = out.mutable_unchecked<2>();
  for (std::size_t k = 0; k < ts.size(); ++k) {
    const Eigen::Matrix<double, N, 1> v = get(ts[k]);
    for (int i = 0; i < N; ++i) m(static_cast<py::ssize_t>(k), i) = v(i);
  }
  return out;
}

// {field: array}: (M, 3) vectors, (M, 3, 3) rotations, (M, 4) quaternions, (M,) scalars.
py::dict plan_arrays(const miem::TargetPlan& p) {
  using V3 = Eigen::Matrix<double, 3, 1>;
  const auto& ts = p.targets;
  const auto M = static_cast<py::ssize_t>(ts.size());
  py::dict d;
  d["point"] = stack<3>(ts, [](const miem::Target& t) -> V3 { return t.point; });
  d["point_scan"] = stack<3>(ts, [](const miem::Target& t) -> V3 { return t.point_scan; });
  d["normal"] = stack<3>(ts, [](const miem::Target& t) -> V3 { return t.normal; });
  d["position"] = stack<3>(ts, [](const miem::Target& t) -> V3 { return t.position; });
  d["approach_point"] = stack<3>(ts, [](const miem::Target& t) -> V3 { return t.approach_point; });
  d["retract_point"] = stack<3>(ts, [](const miem::Target& t) -> V3 { return t.retract_point; });
  d["abc_deg"] = stack<3>(ts, [](const miem::Target& t) -> V3 { return t.abc_deg; });
  d["quaternion"] = stack<4>(ts, [](const miem::Target& t) -> Eigen::Vector4d { return t.quaternion; });
  py::array_t<double> rot({M, py::ssize_t{3}, py::ssize_t{3}});
  py::array_t<double> depth(M), area(M), volume(M);
  py::array_t<std::int64_t> count(M), peak(M);
  auto r = rot.mutable_unchecked<3>();
  for (py::ssize_t k = 0; k < M; ++k) {
    const miem::Target& t = ts[static_cast<std::size_t>(k)];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) r(k, i, j) = t.rotation(i, j);
    depth.mutable_at(k) = t.depth;
    area.mutable_at(k) = t.area;
    volume.mutable_at(k) = t.volume;
    count.mutable_at(k) = t.count;
    peak.mutable_at(k) = t.peak_index;
  }
  d["rotation"] = rot;
  d["depth"] = depth;
  d["area"] = area;
  d["volume"] = volume;
  d["count"] = count;
  d["peak_index"] = peak;
  py::list ids;
  for (const miem::Target& t : ts) ids.append(py::tuple(py::cast(t.defect_ids)));
  d["defect_ids"] = ids;
  return d;
}

}  // namespace

void bind_targets(py::module_& m) {
  py::enum_<miem::TargetAnchor>(m, "TargetAnchor")
      .value("peak", miem::TargetAnchor::kPeak)
      .value("centroid", miem::TargetAnchor::kCentroid);

  py::class_<miem::TargetParams>(m, "TargetParams")
      .def(py::init<>())
      .def_readwrite("anchor", &miem::TargetParams::anchor)
      .def_readwrite("protrusions", &miem::TargetParams::protrusions)
      .def_readwrite("pits", &miem::TargetParams::pits)
      .def_readwrite("isolated", &miem::TargetParams::isolated)
      .def_readwrite("min_height", &miem::TargetParams::min_height)
      .def_readwrite("min_area", &miem::TargetParams::min_area)
      .def_readwrite("min_count", &miem::TargetParams::min_count)
      .def_readwrite("tool_radius", &miem::TargetParams::tool_radius)
      .def_readwrite("edge_clearance", &miem::TargetParams::edge_clearance)
      .def_readwrite("standoff", &miem::TargetParams::standoff)
      .def_readwrite("approach", &miem::TargetParams::approach)
      .def_readwrite("retract", &miem::TargetParams::retract)
      .def_readwrite("toward_sensor", &miem::TargetParams::toward_sensor)
      .def_readwrite("x_reference", &miem::TargetParams::x_reference)
      .def_readwrite("start", &miem::TargetParams::start)
      .def_readwrite("order", &miem::TargetParams::order)
      .def_readwrite("point_area", &miem::TargetParams::point_area)
      .def_readwrite("roi_polygon", &miem::TargetParams::roi_polygon)
      .def("validate", [](const miem::TargetParams& p) { miem::validate(p); });

  py::class_<miem::Target>(m, "Target")
      .def_readonly("point", &miem::Target::point)
      .def_readonly("point_scan", &miem::Target::point_scan)
      .def_readonly("normal", &miem::Target::normal)
      .def_readonly("rotation", &miem::Target::rotation)
      .def_readonly("position", &miem::Target::position)
      .def_readonly("approach_point", &miem::Target::approach_point)
      .def_readonly("retract_point", &miem::Target::retract_point)
      .def_readonly("quaternion", &miem::Target::quaternion)
      .def_readonly("abc_deg", &miem::Target::abc_deg)
      .def_readonly("depth", &miem::Target::depth)
      .def_readonly("area", &miem::Target::area)
      .def_readonly("volume", &miem::Target::volume)
      .def_readonly("count", &miem::Target::count)
      .def_readonly("peak_index", &miem::Target::peak_index)
      .def_readonly("defect_ids", &miem::Target::defect_ids);

  py::class_<miem::TargetPlan>(m, "TargetPlan")
      .def_readonly("targets", &miem::TargetPlan::targets)
      .def_readonly("path_length", &miem::TargetPlan::path_length)
      .def_readonly("defects_in", &miem::TargetPlan::defects_in)
      .def_readonly("defects_used", &miem::TargetPlan::defects_used)
      .def("arrays", &plan_arrays,
           "Every target field stacked over the targets: one array per field (fast to read)")
      .def_property_readonly("rejected", [](const miem::TargetPlan& p) {
        py::dict d;
        d["kind"] = p.rejected.kind;
        d["height"] = p.rejected.height;
        d["size"] = p.rejected.size;
        d["roi"] = p.rejected.roi;
        d["edge"] = p.rejected.edge;
        return d;
      });

  m.def("plan_targets", &plan, py::arg("grid"), py::arg("labels"), py::arg("height"),
        py::arg("defects"), py::arg("transforms"), py::arg("params"), py::arg("roi_mask"));
  m.def("check_transforms", [](const py::array_t<double, py::array::c_style | py::array::forcecast>& t,
                               py::ssize_t rows) -> py::object {
    const char* msg = miem::check_transforms({t.data(), t.size() / 16}, rows);
    return msg ? py::object(py::str(msg)) : py::object(py::none());
  });
  m.def("quaternion_from_rotation", &miem::quaternion_from_rotation, py::arg("R"));
  m.def("abc_from_rotation", &miem::abc_from_rotation, py::arg("R"));
  m.def("order_path", [](const std::vector<Eigen::Vector3d>& pts, const Eigen::Vector3d& start) {
    py::gil_scoped_release nogil;
    return miem::order_path(pts, start);
  }, py::arg("points"), py::arg("start"));
}
