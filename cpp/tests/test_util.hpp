// Shared helpers of the C++ tests: the expectation-file reader (files written by
// data/make_expectations.py from the NumPy reference) and a seeded scan generator.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <limits>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "miem/organized.hpp"

namespace miem::test {

inline constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

/// One reference defect as stored: kind, peak height, member indices.
struct RefDefect {
  std::string kind;
  double peak_height = kNaN;
  std::vector<std::int64_t> indices;
};

/// One expectation case.
struct Expectation {
  std::string name, dtype;
  std::ptrdiff_t rows = 0, cols = 0;
  DetectParams params = paper_params();  // the files give the angle test only
  std::vector<double> grid;  // rows * cols * 3, row-major
  std::vector<int> labels, flags;
  std::vector<double> angle, height;
  int iterations = 0;
  bool has_plane = false;
  double normal[3] = {0, 0, 0};
  double d = 0, rms = 0;
  std::int64_t n_points = 0;
  std::vector<RefDefect> defects;
};

inline double parse_double(const std::string& s) {
  return std::strtod(s.c_str(), nullptr);  // reads "nan" too
}

/// Reads one expectation file; throws std::runtime_error on a malformed file.
inline Expectation read_expectation(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path);
  Expectation e;
  std::string line, key;
  auto expect_key = [&](const std::string& want) {
    if (!(in >> key) || key != want) throw std::runtime_error(path + ": expected " + want);
  };
  std::getline(in, line);
  if (line.rfind("miem-expectation 1", 0) != 0) throw std::runtime_error(path + ": bad magic");
  auto read_n = [&](std::size_t n, auto&& put) {
    std::string tok;
    for (std::size_t i = 0; i < n; ++i) {
      if (!(in >> tok)) throw std::runtime_error(path + ": truncated");
      put(tok);
    }
  };
  while (in >> key) {
    if (key == "#") {
      std::getline(in, line);
    } else if (key == "name") {
      in >> e.name;
    } else if (key == "dtype") {
      in >> e.dtype;
    } else if (key == "rows") {
      in >> e.rows;
    } else if (key == "cols") {
      in >> e.cols;
    } else if (key == "theta0") {
      in >> line;
      e.params.theta0_deg = parse_double(line);
    } else if (key == "scales") {
      int n = 0;
      in >> n;
      e.params.scales.assign(static_cast<std::size_t>(n), 1);
      for (int& s : e.params.scales) in >> s;
    } else if (key == "max_gap") {
      in >> e.params.max_gap;
    } else if (key == "min_step") {
      in >> line;
      e.params.min_step = parse_double(line);
    } else if (key == "max_reach") {
      in >> e.params.max_reach;
    } else if (key == "min_directions") {
      in >> e.params.min_directions;
    } else if (key == "max_iterations") {
      in >> e.params.max_iterations;
    } else if (key == "window") {
      in >> e.params.window;
    } else if (key == "grid") {
      read_n(static_cast<std::size_t>(e.rows * e.cols * 3),
             [&](const std::string& t) { e.grid.push_back(parse_double(t)); });
    } else if (key == "labels") {
      for (std::ptrdiff_t r = 0; r < e.rows; ++r) {
        in >> line;
        if (static_cast<std::ptrdiff_t>(line.size()) != e.cols) {
          throw std::runtime_error(path + ": bad label row");
        }
        for (char ch : line) e.labels.push_back(ch - '0');
      }
    } else if (key == "flags") {
      read_n(static_cast<std::size_t>(e.rows * e.cols),
             [&](const std::string& t) { e.flags.push_back(std::stoi(t)); });
    } else if (key == "angle") {
      read_n(static_cast<std::size_t>(e.rows * e.cols),
             [&](const std::string& t) { e.angle.push_back(parse_double(t)); });
    } else if (key == "height") {
      read_n(static_cast<std::size_t>(e.rows * e.cols),
             [&](const std::string& t) { e.height.push_back(parse_double(t)); });
    } else if (key == "iterations") {
      in >> e.iterations;
    } else if (key == "plane") {
      int has = 0;
      in >> has;
      e.has_plane = has != 0;
      if (e.has_plane) {
        std::string t[5];
        for (auto& s : t) in >> s;
        for (int i = 0; i < 3; ++i) e.normal[i] = parse_double(t[i]);
        e.d = parse_double(t[3]);
        e.rms = parse_double(t[4]);
        in >> e.n_points;
      }
    } else if (key == "defects") {
      std::size_t n = 0;
      in >> n;
      for (std::size_t i = 0; i < n; ++i) {
        expect_key("defect");
        RefDefect d;
        std::size_t count = 0;
        in >> d.kind >> line >> count;
        d.peak_height = parse_double(line);
        d.indices.resize(count);
        for (auto& idx : d.indices) in >> idx;
        e.defects.push_back(std::move(d));
      }
    } else if (key == "end") {
      return e;
    } else {
      throw std::runtime_error(path + ": unknown key " + key);
    }
    if (!in) throw std::runtime_error(path + ": read error after " + key);
  }
  throw std::runtime_error(path + ": missing end");
}

/// What make_scan puts into a scan.
struct ScanOptions {
  double dx = 0.25, dy = 0.3;   // spacing along / across the profiles
  double noise = 0.002;         // z noise (quantised to 1e-3 afterwards)
  double dropout_rate = 0.01;   // isolated dropouts
  int spikes = 6, pits = 4, spatters = 3, wedges = 4, dust = 2;
  bool nan_rows = true;         // a whole profile lost, and a run of dropouts along a profile
};

/// A seeded synthetic organized scan (rows x cols x 3, row-major) with burr tips, pits, 2x2
/// spatter, wedge burrs across the profiles (they need several passes: removals cascade across
/// rows), floating dust, scattered dropouts and a lost profile.
inline std::vector<double> make_scan(std::ptrdiff_t rows, std::ptrdiff_t cols, std::uint64_t seed,
                                     const ScanOptions& o = {}) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  auto gauss = [&]() {  // Box-Muller: the same numbers on every standard library
    const double u1 = std::max(uni(rng), 1e-300), u2 = uni(rng);
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(6.283185307179586 * u2);
  };
  std::vector<double> g(static_cast<std::size_t>(rows * cols * 3));
  auto at = [&](std::ptrdiff_t r, std::ptrdiff_t c, int k) -> double& {
    return g[static_cast<std::size_t>((r * cols + c) * 3 + k)];
  };
  const double xc = 0.5 * cols * o.dx;
  for (std::ptrdiff_t r = 0; r < rows; ++r) {
    for (std::ptrdiff_t c = 0; c < cols; ++c) {
      const double x = c * o.dx, y = r * o.dy;
      at(r, c, 0) = x;
      at(r, c, 1) = y;
      at(r, c, 2) = std::round((0.4 * std::exp(-(x - xc) * (x - xc) / 50.0) + 0.01 * y +
                                o.noise * gauss()) * 1000.0) / 1000.0;
    }
  }
  auto pick = [&](std::ptrdiff_t n, std::ptrdiff_t margin) {
    return margin + static_cast<std::ptrdiff_t>(uni(rng) * static_cast<double>(n - 2 * margin));
  };
  if (rows < 8 || cols < 8) return g;
  for (int i = 0; i < o.spikes; ++i) at(pick(rows, 1), pick(cols, 1), 2) += 0.5 + uni(rng);
  for (int i = 0; i < o.pits; ++i) at(pick(rows, 1), pick(cols, 1), 2) -= 0.4 + uni(rng);
  for (int i = 0; i < o.spatters; ++i) {
    const std::ptrdiff_t r = pick(rows - 1, 1), c = pick(cols - 1, 1);
    const double h = 0.4 + 0.5 * uni(rng);
    for (int a = 0; a < 2; ++a)
      for (int b = 0; b < 2; ++b) at(r + a, c + b, 2) += h;
  }
  const double wedge[6] = {2.4, 1.8, 1.3, 0.9, 0.6, 0.35};
  for (int i = 0; i < o.wedges && rows > 12; ++i) {
    const std::ptrdiff_t r = pick(rows - 6, 1), c = pick(cols - 1, 1);
    const bool down = uni(rng) < 0.5;
    for (int k = 0; k < 6; ++k) {
      const std::ptrdiff_t rr = down ? r + k : r + 5 - k;
      at(rr, c, 2) += wedge[k];
      at(rr, c + 1, 2) += 0.9 * wedge[k];
    }
  }
  for (int i = 0; i < o.dust; ++i) at(pick(rows, 2), pick(cols, 2), 2) += 5.0 + uni(rng);
  const double nan = kNaN;
  for (std::ptrdiff_t r = 0; r < rows; ++r)
    for (std::ptrdiff_t c = 0; c < cols; ++c)
      if (uni(rng) < o.dropout_rate) at(r, c, 0) = at(r, c, 1) = at(r, c, 2) = nan;
  if (o.nan_rows) {
    const std::ptrdiff_t r = pick(rows, 2);
    for (std::ptrdiff_t c = 0; c < cols; ++c) at(r, c, 0) = at(r, c, 1) = at(r, c, 2) = nan;
    const std::ptrdiff_t r2 = pick(rows, 2), c2 = pick(cols - 4, 0);
    for (std::ptrdiff_t c = c2; c < c2 + 4; ++c) at(r2, c, 2) = nan;
  }
  return g;
}

}  // namespace miem::test
