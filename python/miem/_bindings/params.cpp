// pybind11 bindings of the parameter types (cpp/include/miem/params.hpp): the read-write fields
// each type lists in visit_fields() (with unit and help), check() as (code, message), and the
// presets. python/miem/params.py builds miem.DetectParams from these fields and defaults.
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <deque>
#include <string>

#include "miem/params.hpp"
#include "miem/stream.hpp"

namespace py = pybind11;

namespace {

py::tuple status_tuple(const miem::Status& st) {
  return py::make_tuple(static_cast<int>(st.code), st.message);
}

}  // namespace

// Registers T's own fields (T::visit_fields) as read-write attributes documented "[unit] help",
// and T.fields() -> [(name, unit, help)] in declaration order, which miem.DetectParams, the
// command line and miem.dask are generated from.
template <class T, class Cls>
void def_fields(Cls& cls) {
  static std::deque<std::string> docs;  // the attributes' docstrings live as long as the module
  T::visit_fields([&cls](const miem::FieldInfo& f, auto member) {
    docs.push_back(*f.unit ? "[" + std::string(f.unit) + "] " + f.help : std::string(f.help));
    cls.def_readwrite(f.name, member, docs.back().c_str());
  });
  cls.def_static("fields", [] {
    py::list out;
    T::visit_fields([&out](const miem::FieldInfo& f, auto) {
      out.append(py::make_tuple(f.name, f.unit, f.help));
    });
    return out;
  }, "[(name, unit, help)] of this type's own fields, in declaration order.");
}

void bind_params(py::module_& m) {
  py::enum_<miem::HeightMode>(m, "HeightMode")
      .value("ALL", miem::HeightMode::kAll)
      .value("ABNORMAL", miem::HeightMode::kAbnormal);

  py::class_<miem::AngleParams> angle(
      m, "AngleParams", "The angle test and its iteration (batch, stream and clouds).");
  angle.def(py::init<>());
  def_fields<miem::AngleParams>(angle);
  angle.def("check", [](const miem::AngleParams& p) { return status_tuple(p.check()); });

  py::class_<miem::GridParams> grid(
      m, "GridParams", "Organized grids only: search, heights, height and edge tests.");
  grid.def(py::init<>());
  def_fields<miem::GridParams>(grid);
  grid.def("height_test", &miem::GridParams::height_test)
      .def("edge_test", &miem::GridParams::edge_test)
      .def("check", [](const miem::GridParams& p) { return status_tuple(p.check()); });

  py::class_<miem::CloudParams> cloud(m, "CloudParams",
                                      "Unorganized clouds only: neighbourhood, K, height test.");
  cloud.def(py::init<>());
  def_fields<miem::CloudParams>(cloud);
  cloud.def("check", [](const miem::CloudParams& p) { return status_tuple(p.check()); });

  py::class_<miem::DetectParams, miem::AngleParams, miem::GridParams> detect(
      m, "DetectParams", "Organized detection parameters; default-constructed: 'recommended'.");
  detect.def(py::init<>());
  def_fields<miem::DetectParams>(detect);
  detect.def("check", [](const miem::DetectParams& p) { return status_tuple(p.check()); });

  py::class_<miem::PointsDetectParams, miem::AngleParams, miem::CloudParams> points(
      m, "PointsDetectParams", "Unorganized detection parameters.");
  points.def(py::init<>());
  def_fields<miem::PointsDetectParams>(points);
  points.def("check", [](const miem::PointsDetectParams& p) { return status_tuple(p.check()); });

  m.def("paper_params", &miem::paper_params, "The paper's method exactly.");
  m.def("recommended_params", &miem::recommended_params, "The recommended preset.");
  m.def("paper_points_params", &miem::paper_points_params, "The paper's method on clouds.");
  m.def("stream_lag", &miem::stream_lag, py::arg("params"),
        "Profiles between pushing a row into a ProfileStream and getting it back final.");
  m.def("stream_default_params", &miem::stream_default_params,
        "The default parameters of a ProfileStream.");
  m.def(
      "check_stream_params",
      [](std::ptrdiff_t width, const miem::DetectParams& p) {
        return status_tuple(miem::check_stream_params(width, p));
      },
      py::arg("width"), py::arg("params"));
}
