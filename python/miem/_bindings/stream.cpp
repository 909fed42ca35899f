// pybind11 bindings of miem::ProfileStream (streaming detection): conversion and validation only.
// Exposed as miem._core.ProfileStream32 / ProfileStream64 (float / double storage); the typed
// wrapper is python/miem/stream.py.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <atomic>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "common.hpp"
#include "miem/stream.hpp"

namespace py = pybind11;

namespace {

template <typename T>
class PyProfileStream {
 public:
  PyProfileStream(std::ptrdiff_t width, const miem::DetectParams& params)
      : stream_(width, params) {}

  // Returns (status code, message, row index or -1, labels or None, heights or None, defects:
  // the (id, indices, centroid, normal, peak, mean, extent, kind) tuples this call made final).
  py::tuple push(const py::array& profile) {
    const Exclusive guard(busy_);
    if (!miem::bindings::is_dtype<T>(profile)) {
      throw std::invalid_argument("profile: dtype must match the stream's dtype");
    }
    miem::bindings::require_aligned<T>(profile, "profile");
    if (profile.ndim() != 2 || profile.shape(1) != 3) {
      throw std::invalid_argument("profile: expected shape (width, 3)");
    }
    const miem::PointsView<T> view = miem::bindings::points_view<T>(profile, "profile");
    miem::StreamRow row;
    miem::Status st;
    {
      py::gil_scoped_release nogil;
      st = stream_.push(view, &row);
    }
    return py::make_tuple(static_cast<int>(st.code), st.message, row.index, labels(row),
                          heights(row), defects(row));
  }

  // Every pending row as (row index, labels, heights, defects), oldest first.
  py::list flush() {
    const Exclusive guard(busy_);
    py::list out;
    miem::StreamRow row;
    while (stream_.flush(&row)) {
      out.append(py::make_tuple(row.index, labels(row), heights(row), defects(row)));
    }
    return out;
  }

  void reset() {
    const Exclusive guard(busy_);
    stream_.reset();
  }
  std::ptrdiff_t width() const { return stream_.width(); }
  int lag() const { return stream_.lag(); }
  int reach() const { return stream_.reach(); }
  std::int64_t rows_pushed() const { return stream_.rows_pushed(); }
  std::int64_t edge_candidates() const { return stream_.edge_candidates(); }
  std::int64_t rows_emitted() const { return stream_.rows_emitted(); }
  bool finished() const { return stream_.finished(); }
  // The min_step in use: None while "auto" waits for its rows or when off.
  std::optional<double> min_step() const {
    if (!stream_.min_step_decided() || stream_.min_step() < 0.0) return std::nullopt;
    return stream_.min_step();
  }
  bool min_step_decided() const { return stream_.min_step_decided(); }
  // The z_resolution in use: None while "auto" waits for its rows (-1 until then) or when off.
  std::optional<double> z_resolution() const {
    if (stream_.z_resolution() < 0.0) return std::nullopt;
    return stream_.z_resolution();
  }
  // The z_noise in use: None while "auto" waits for its rows (-1 until then) or when off.
  std::optional<double> z_noise() const {
    if (stream_.z_noise() < 0.0) return std::nullopt;
    return stream_.z_noise();
  }

 private:
  // A stream is one sequence of profiles: push/flush/reset from two threads at once would
  // interleave rows and corrupt the ring, so an overlapping call is refused (RuntimeError)
  // instead of serialised in an order nobody chose. The flag is held while the GIL is released.
  class Exclusive {
   public:
    explicit Exclusive(std::atomic<bool>& busy) : busy_(busy) {
      if (busy_.exchange(true, std::memory_order_acquire)) {
        throw std::runtime_error(
            "ProfileStream: called from two threads at once; a stream takes its profiles in "
            "order from one thread at a time (use one stream per scanner, or a lock)");
      }
    }
    ~Exclusive() { busy_.store(false, std::memory_order_release); }
    Exclusive(const Exclusive&) = delete;
    Exclusive& operator=(const Exclusive&) = delete;

   private:
    std::atomic<bool>& busy_;
  };

  py::object labels(const miem::StreamRow& row) const {
    if (!row.ready()) return py::none();
    py::array_t<std::uint8_t> a(stream_.width());
    std::copy(row.labels, row.labels + stream_.width(), a.mutable_data());
    return std::move(a);
  }

  py::object heights(const miem::StreamRow& row) const {
    if (!row.ready()) return py::none();
    py::array_t<double> a(stream_.width());
    std::copy(row.height, row.height + stream_.width(), a.mutable_data());
    return std::move(a);
  }

  static py::list defects(const miem::StreamRow& row) {
    return miem::bindings::defect_list(
        std::vector<miem::Defect>(row.defects, row.defects + row.n_defects));
  }

  miem::ProfileStream<T> stream_;
  std::atomic<bool> busy_{false};
};

template <typename T>
void bind_one(py::module_& m, const char* name) {
  py::class_<PyProfileStream<T>>(m, name)
      .def(py::init<std::ptrdiff_t, const miem::DetectParams&>(), py::arg("width"),
           py::arg("params"))
      .def("push", &PyProfileStream<T>::push, py::arg("profile"))
      .def("flush", &PyProfileStream<T>::flush)
      .def("reset", &PyProfileStream<T>::reset)
      .def_property_readonly("width", &PyProfileStream<T>::width)
      .def_property_readonly("lag", &PyProfileStream<T>::lag)
      .def_property_readonly("reach", &PyProfileStream<T>::reach)
      .def_property_readonly("rows_pushed", &PyProfileStream<T>::rows_pushed)
      .def_property_readonly("edge_candidates", &PyProfileStream<T>::edge_candidates)
      .def_property_readonly("rows_emitted", &PyProfileStream<T>::rows_emitted)
      .def_property_readonly("finished", &PyProfileStream<T>::finished)
      .def_property_readonly("min_step", &PyProfileStream<T>::min_step)
      .def_property_readonly("min_step_decided", &PyProfileStream<T>::min_step_decided)
      .def_property_readonly("z_resolution", &PyProfileStream<T>::z_resolution)
      .def_property_readonly("z_noise", &PyProfileStream<T>::z_noise);
}

}  // namespace

void bind_stream(py::module_& m) {
  bind_one<float>(m, "ProfileStream32");
  bind_one<double>(m, "ProfileStream64");
}
