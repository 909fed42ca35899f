// pybind11 bindings of the parameter types (cpp/include/miem/params.hpp): read-write fields with
// their units, check() as (code, message), and the presets. The typed Python mirror that users
// see is python/miem/params.py; tests tie its defaults to these.
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "miem/params.hpp"
#include "miem/stream.hpp"

namespace py = pybind11;

namespace {

py::tuple status_tuple(const miem::Status& st) {
  return py::make_tuple(static_cast<int>(st.code), st.message);
}

}  // namespace

void bind_params(py::module_& m) {
  py::enum_<miem::HeightMode>(m, "HeightMode")
      .value("ALL", miem::HeightMode::kAll)
      .value("ABNORMAL", miem::HeightMode::kAbnormal);

  py::class_<miem::AngleParams>(m, "AngleParams",
                                "The angle test and its iteration (batch, stream and clouds).")
      .def(py::init<>())
      .def_readwrite("theta0_deg", &miem::AngleParams::theta0_deg,
                     "degrees: a direction is flagged when its angle <= theta0 (0 < theta0 < 180)")
      .def_readwrite("theta0_auto", &miem::AngleParams::theta0_auto,
                     "derive theta0 from the scan's own angles (grids only)")
      .def_readwrite("scales", &miem::AngleParams::scales,
                     "neighbour scales, each >= 1 (cells on grids, multiples of min_step on clouds)")
      .def_readwrite("min_directions", &miem::AngleParams::min_directions,
                     "flagged directions needed for ABNORMAL; 0: all available")
      .def_readwrite("max_iterations", &miem::AngleParams::max_iterations,
                     "passes at most (>= 1), angle passes and height passes each")
      .def("check", [](const miem::AngleParams& p) { return status_tuple(p.check()); });

  py::class_<miem::GridParams>(m, "GridParams", "Organized grids only: search, heights, height test.")
      .def(py::init<>())
      .def_readwrite("max_gap", &miem::GridParams::max_gap,
                     "cells: unusable cells that may be skipped to find a neighbour (>= 0)")
      .def_readwrite("min_step", &miem::GridParams::min_step,
                     "length: neighbours at least s * min_step away; < 0: off")
      .def_readwrite("min_step_auto", &miem::GridParams::min_step_auto,
                     "min_step from the grid's spacing and noise (SPEC min_step='auto')")
      .def_readwrite("max_reach", &miem::GridParams::max_reach,
                     "cells: extra cells searched with min_step (>= 1)")
      .def_readwrite("window", &miem::GridParams::window,
                     "cells: side of the local-plane window (odd >= 3)")
      .def_readwrite("height_mode", &miem::GridParams::height_mode, "which cells get a height")
      .def_readwrite("height_abs", &miem::GridParams::height_abs,
                     "length: height test, |height| above this is ABNORMAL; <= 0: off")
      .def_readwrite("height_k", &miem::GridParams::height_k,
                     "multiple of the window plane's rms: height test; <= 0: off")
      .def_readwrite("edge_extent", &miem::GridParams::edge_extent,
                     "cells: EDGE groups this compact are height-tested too (>= 0)")
      .def_readwrite("edge_k", &miem::GridParams::edge_k,
                     "multiple of the sub-window rms: edge test (SPEC 'Edge test'); 0: off")
      .def_readwrite("edge_window", &miem::GridParams::edge_window,
                     "cells: edge test sub-window side (odd >= 3)")
      .def("height_test", &miem::GridParams::height_test)
      .def("edge_test", &miem::GridParams::edge_test)
      .def("check", [](const miem::GridParams& p) { return status_tuple(p.check()); });

  py::class_<miem::CloudParams>(m, "CloudParams", "Unorganized clouds only: neighbourhood, K.")
      .def(py::init<>())
      .def_readwrite("radius", &miem::CloudParams::radius,
                     "length: neighbourhood radius (> 0); None: 5 x spacing")
      .def_readwrite("num_directions", &miem::CloudParams::num_directions,
                     "K tangent-plane directions, 2..8")
      .def_readwrite("min_step", &miem::CloudParams::min_step,
                     "length: shortest tangent offset (>= 0); None: 0.5 x spacing")
      .def_readwrite("link", &miem::CloudParams::link,
                     "length: defect linking distance (> 0); None: radius")
      .def_readwrite("min_group", &miem::CloudParams::min_group,
                     "points: 0 off; else >= 3, smaller floating groups are ABNORMAL")
      .def_readwrite("height_abs", &miem::CloudParams::height_abs,
                     "length: height test, |height| above this is ABNORMAL; <= 0: off")
      .def_readwrite("height_k", &miem::CloudParams::height_k,
                     "multiple of the local plane's rms: height test; <= 0: off")
      .def_readwrite("edge_extent", &miem::CloudParams::edge_extent,
                     "spacings: EDGE groups this compact are height-tested too (>= 0)")
      .def_readwrite("height_radius", &miem::CloudParams::height_radius,
                     "length: height-plane radius (> 0); None: 2 x radius")
      .def_readwrite("merge_distance", &miem::CloudParams::merge_distance,
                     "length: points this close are one point (>= 0; 0: equal coordinates)")
      .def_readwrite("spacing", &miem::CloudParams::spacing,
                     "length: the point spacing (> 0); None: median nearest-neighbour distance")
      .def_readwrite("edge_k", &miem::CloudParams::edge_k,
                     "multiple of the sector rms: edge test (needs the height test); 0: off")
      .def_readwrite("isolated_k", &miem::CloudParams::isolated_k,
                     "multiple of the surroundings rms: the height test's isolated-point rule; "
                     "0: off")
      .def_readwrite("edge_radius", &miem::CloudParams::edge_radius,
                     "length: edge-test sector radius (> 0); None: height_radius")
      .def("check", [](const miem::CloudParams& p) { return status_tuple(p.check()); });

  py::class_<miem::DetectParams, miem::AngleParams, miem::GridParams>(
      m, "DetectParams", "Organized detection parameters; default-constructed: 'recommended'.")
      .def(py::init<>())
      .def_readwrite("num_threads", &miem::DetectParams::num_threads, "0: all cores")
      .def("check", [](const miem::DetectParams& p) { return status_tuple(p.check()); });

  py::class_<miem::PointsDetectParams, miem::AngleParams, miem::CloudParams>(
      m, "PointsDetectParams", "Unorganized detection parameters.")
      .def(py::init<>())
      .def_readwrite("height_mode", &miem::PointsDetectParams::height_mode,
                     "which points get a height")
      .def_readwrite("num_threads", &miem::PointsDetectParams::num_threads, "0: all cores")
      .def("check", [](const miem::PointsDetectParams& p) { return status_tuple(p.check()); });

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
