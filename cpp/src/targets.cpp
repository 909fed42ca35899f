// Grinding targets: defects -> selected, merged, ordered tool poses in the base frame.
// The rules are in docs/SPEC.md "Grinding targets"; miem.reference_targets is the NumPy oracle.
#include "miem/targets.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <stdexcept>

#include <Eigen/Geometry>

namespace miem {

namespace {

constexpr double kRigidTol = 1e-5;

bool all_finite(const Eigen::Vector3d& v) { return v.allFinite(); }
bool all_nan(const Eigen::Vector3d& v) { return v.array().isNaN().all(); }

const char* check_target_params(const TargetParams& p) noexcept {
  const auto nonneg = [](double v) { return std::isfinite(v) && v >= 0.0; };
  if (!nonneg(p.min_height)) return "min_height: must be a finite length >= 0";
  if (!nonneg(p.min_area)) return "min_area: must be a finite area >= 0";
  if (p.min_count < 1) return "min_count: must be an integer >= 1";
  if (!nonneg(p.tool_radius)) return "tool_radius: must be a finite length >= 0";
  if (!nonneg(p.edge_clearance)) return "edge_clearance: must be a finite length >= 0";
  if (!std::isfinite(p.standoff)) return "standoff: must be a finite length";
  if (!nonneg(p.approach)) return "approach: must be a finite length >= 0";
  if (!nonneg(p.retract)) return "retract: must be a finite length >= 0";
  if (!nonneg(p.point_area)) return "point_area: must be a finite area >= 0";
  if (!all_finite(p.toward_sensor) || p.toward_sensor.norm() == 0.0) {
    return "toward_sensor: must be a finite non-zero vector";
  }
  if (!all_nan(p.x_reference) && (!all_finite(p.x_reference) || p.x_reference.norm() == 0.0)) {
    return "x_reference: must be a finite non-zero vector (or all NaN for the scan direction)";
  }
  if (!all_nan(p.start) && !all_finite(p.start)) {
    return "start: must be a finite point (or all NaN for none)";
  }
  if (p.anchor != TargetAnchor::kPeak && p.anchor != TargetAnchor::kCentroid) {
    return "anchor: must be peak or centroid";
  }
  if (!p.roi_polygon.empty()) {
    if (p.roi_polygon.size() < 3) return "roi_polygon: needs at least 3 vertices";
    for (const auto& v : p.roi_polygon) {
      if (!v.allFinite()) return "roi_polygon: vertices must be finite";
    }
  }
  return nullptr;
}

/// Even-odd rule; points on an edge count as inside only by the arithmetic's luck (measure zero).
bool inside_polygon(const std::vector<Eigen::Vector2d>& poly, double x, double y) {
  bool in = false;
  for (std::size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    const Eigen::Vector2d& a = poly[i];
    const Eigen::Vector2d& b = poly[j];
    if ((a.y() > y) != (b.y() > y) && x < (b.x() - a.x()) * (y - a.y()) / (b.y() - a.y()) + a.x()) {
      in = !in;
    }
  }
  return in;
}

struct Rigid {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
};

std::vector<Rigid> read_transforms(const TransformsView& v) {
  std::vector<Rigid> out(static_cast<std::size_t>(v.count));
  for (std::ptrdiff_t k = 0; k < v.count; ++k) {
    const double* m = v.data + 16 * k;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) out[k].R(r, c) = m[4 * r + c];
      out[k].t(r) = m[4 * r + 3];
    }
  }
  return out;
}

/// A selected defect, before merging.
struct Candidate {
  int id = 0;
  double depth = 0.0;
  double area = 0.0, volume = 0.0;
  int count = 0;
  std::int64_t peak = -1;
  std::size_t transform = 0;
  Eigen::Vector3d anchor, anchor_scan, normal, sum_base, sum_scan;
};

/// Deeper first: larger |depth|, NaN last, then smaller id.
bool deeper(const Candidate& a, const Candidate& b) {
  const bool na = std::isnan(a.depth), nb = std::isnan(b.depth);
  if (na != nb) return nb;
  if (!na && std::abs(a.depth) != std::abs(b.depth)) return std::abs(a.depth) > std::abs(b.depth);
  return a.id < b.id;
}

int find_root(std::vector<int>& parent, int i) {
  while (parent[i] != i) {
    parent[i] = parent[parent[i]];
    i = parent[i];
  }
  return i;
}

/// Tool frame: z = -normal, x = the reference projected onto the tangent plane, y = z x x.
Eigen::Matrix3d tool_rotation(const Eigen::Vector3d& normal, const Eigen::Vector3d& ref,
                              const Eigen::Matrix3d& R_scan) {
  const Eigen::Vector3d z = -normal;
  Eigen::Vector3d x = ref - ref.dot(z) * z;
  if (x.norm() <= 1e-9 * ref.norm()) {  // reference along the tool axis: the scan x axis
    const Eigen::Vector3d alt = R_scan.col(0);
    x = alt - alt.dot(z) * z;
  }
  if (x.norm() <= 1e-9) {  // still degenerate: the base axis least aligned with z
    Eigen::Index k;
    z.cwiseAbs().minCoeff(&k);
    const Eigen::Vector3d e = Eigen::Vector3d::Unit(k);
    x = e - e.dot(z) * z;
  }
  x.normalize();
  Eigen::Matrix3d R;
  R.col(0) = x;
  R.col(1) = z.cross(x);
  R.col(2) = z;
  return R;
}

double path_length(const std::vector<Eigen::Vector3d>& pts, const std::vector<int>& order,
                   const Eigen::Vector3d& start) {
  double len = 0.0;
  for (std::size_t k = 0; k < order.size(); ++k) {
    if (k > 0) {
      len += (pts[order[k]] - pts[order[k - 1]]).norm();
    } else if (start.allFinite()) {
      len += (pts[order[0]] - start).norm();
    }
  }
  return len;
}

}  // namespace

void validate(const TargetParams& params) {
  if (const char* msg = check_target_params(params)) throw std::invalid_argument(msg);
}

const char* check_transforms(const TransformsView& v, std::ptrdiff_t rows) noexcept {
  if (v.data == nullptr || v.count < 1) return "T_base_sensor: no transform given";
  if (v.count != 1 && v.count != rows) {
    return "T_base_sensor: expected one 4x4 transform or one per profile (grid rows)";
  }
  for (std::ptrdiff_t k = 0; k < v.count; ++k) {
    const double* m = v.data + 16 * k;
    for (int i = 0; i < 16; ++i) {
      if (!std::isfinite(m[i])) return "T_base_sensor: contains NaN or infinite values";
    }
    if (m[12] != 0.0 || m[13] != 0.0 || m[14] != 0.0 || m[15] != 1.0) {
      return "T_base_sensor: the last row of a rigid transform must be 0 0 0 1";
    }
    Eigen::Matrix3d R;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) R(r, c) = m[4 * r + c];
    if ((R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() > kRigidTol) {
      return "T_base_sensor: the rotation part is not orthonormal (not rigid: scale or shear)";
    }
    if (R.determinant() < 0.0) return "T_base_sensor: the rotation part is a reflection (det -1)";
  }
  return nullptr;
}

Eigen::Vector4d quaternion_from_rotation(const Eigen::Matrix3d& R) noexcept {
  Eigen::Quaterniond q(R);
  q.normalize();
  Eigen::Vector4d out(q.w(), q.x(), q.y(), q.z());
  if (out(0) < 0.0) out = -out;
  return out;
}

Eigen::Vector3d abc_from_rotation(const Eigen::Matrix3d& R) noexcept {
  constexpr double kDeg = 180.0 / 3.14159265358979323846;
  const double cb = std::hypot(R(0, 0), R(1, 0));
  const double b = std::atan2(-R(2, 0), cb);
  double a, c;
  if (cb > 1e-9) {
    a = std::atan2(R(1, 0), R(0, 0));
    c = std::atan2(R(2, 1), R(2, 2));
  } else {  // B = +-90: only A - C (or A + C) is defined; take A = 0
    a = 0.0;
    c = std::atan2(-R(1, 2), R(1, 1));
  }
  return {a * kDeg, b * kDeg, c * kDeg};
}

std::vector<int> order_path(const std::vector<Eigen::Vector3d>& points,
                            const Eigen::Vector3d& start) {
  const int n = static_cast<int>(points.size());
  std::vector<int> seq;
  if (n == 0) return seq;
  // Nodes: the points, plus the start as node n when given (fixed first).
  const bool has_start = start.allFinite();
  const auto at = [&](int k) -> const Eigen::Vector3d& { return k == n ? start : points[k]; };
  std::vector<char> used(static_cast<std::size_t>(n), 0);
  seq.reserve(static_cast<std::size_t>(n) + 1);
  int cur;
  if (has_start) {
    seq.push_back(n);
    cur = n;
  } else {
    seq.push_back(0);
    used[0] = 1;
    cur = 0;
  }
  while (static_cast<int>(seq.size()) < n + (has_start ? 1 : 0)) {
    int best = -1;
    double best_d = 0.0;
    for (int k = 0; k < n; ++k) {
      if (used[k]) continue;
      const double d = (points[k] - at(cur)).squaredNorm();
      if (best < 0 || d < best_d) {
        best = k;
        best_d = d;
      }
    }
    used[best] = 1;
    seq.push_back(best);
    cur = best;
  }
  // 2-opt on the open path, first node fixed: reverse seq[i..j] when that shortens it. Nodes
  // are kept in path order (P) with their edge lengths, so a move is judged with two distances.
  const int m = static_cast<int>(seq.size());
  std::vector<Eigen::Vector3d> P(static_cast<std::size_t>(m));
  for (int k = 0; k < m; ++k) P[k] = at(seq[k]);
  std::vector<double> edge(static_cast<std::size_t>(std::max(m - 1, 0)));
  for (int k = 0; k + 1 < m; ++k) edge[k] = (P[k + 1] - P[k]).norm();
  bool improved = true;
  for (int pass = 0; improved && pass < 1000; ++pass) {
    improved = false;
    for (int i = 1; i + 1 < m; ++i) {
      for (int j = i + 1; j < m; ++j) {
        double delta = (P[j] - P[i - 1]).norm() - edge[i - 1];
        if (j + 1 < m) delta += (P[j + 1] - P[i]).norm() - edge[j];
        if (delta < -1e-9 * (1.0 + edge[i - 1])) {
          std::reverse(seq.begin() + i, seq.begin() + j + 1);
          std::reverse(P.begin() + i, P.begin() + j + 1);
          std::reverse(edge.begin() + i, edge.begin() + j);
          edge[i - 1] = (P[i] - P[i - 1]).norm();
          if (j + 1 < m) edge[j] = (P[j + 1] - P[j]).norm();
          improved = true;
        }
      }
    }
  }
  if (has_start) seq.erase(seq.begin());
  return seq;
}

template <typename T>
TargetPlan plan_targets(const GridView<T>& grid, const std::uint8_t* labels, const double* height,
                        const std::vector<Defect>& defects, const TransformsView& T_base_sensor,
                        const TargetParams& p, const std::uint8_t* roi_mask) {
  validate(p);
  if (grid.data == nullptr || grid.rows < 1 || grid.cols < 1) {
    throw std::invalid_argument("grid: must have at least one row and one column");
  }
  if (labels == nullptr) throw std::invalid_argument("labels: must not be null");
  if (height == nullptr) throw std::invalid_argument("height: must not be null");
  if (const char* msg = check_transforms(T_base_sensor, grid.rows)) {
    throw std::invalid_argument(msg);
  }
  const std::ptrdiff_t rows = grid.rows, cols = grid.cols;
  const std::int64_t n = static_cast<std::int64_t>(rows) * cols;
  const std::vector<Rigid> tf = read_transforms(T_base_sensor);
  const auto tf_of = [&](std::int64_t i) -> std::size_t {
    return tf.size() == 1 ? 0 : static_cast<std::size_t>(i / cols);
  };
  const auto scan_at = [&](std::int64_t i) { return grid(i / cols, i % cols); };
  const auto base_at = [&](std::int64_t i) {
    const Rigid& g = tf[tf_of(i)];
    return Eigen::Vector3d(g.R * scan_at(i) + g.t);
  };
  const auto usable = [&](std::ptrdiff_t r, std::ptrdiff_t c) {
    return r >= 0 && r < rows && c >= 0 && c < cols && grid.finite(r, c);
  };
  const Eigen::Vector3d toward = p.toward_sensor.normalized();

  // Base-frame EDGE points, only when the clearance rule is on.
  std::vector<Eigen::Vector3d> edge_pts;
  if (p.edge_clearance > 0.0) {
    for (std::int64_t i = 0; i < n; ++i) {
      if (labels[i] == kEdge && grid.finite(i / cols, i % cols)) edge_pts.push_back(base_at(i));
    }
  }

  TargetPlan plan;
  plan.defects_in = static_cast<int>(defects.size());
  std::vector<Candidate> cands;
  std::vector<std::int64_t> members;
  std::vector<double> areas;
  for (const Defect& d : defects) {
    for (std::int64_t i : d.indices) {
      if (i < 0 || i >= n) throw std::invalid_argument("defects: a point index is outside the grid");
    }
    const bool kind_ok = (d.kind == DefectKind::kProtrusion && p.protrusions) ||
                         (d.kind == DefectKind::kPit && p.pits) ||
                         (d.kind == DefectKind::kIsolated && p.isolated);
    if (!kind_ok) {
      ++plan.rejected.kind;
      continue;
    }
    if (p.min_height > 0.0 && !(std::abs(d.peak_height) >= p.min_height)) {
      ++plan.rejected.height;
      continue;
    }
    // Members: finite ABNORMAL points only (EDGE and NORMAL points are never targeted).
    members.clear();
    for (std::int64_t i : d.indices) {
      if (labels[i] == kAbnormal && grid.finite(i / cols, i % cols)) members.push_back(i);
    }
    if (members.empty() || static_cast<int>(members.size()) < p.min_count) {
      ++plan.rejected.size;
      continue;
    }
    std::int64_t peak = -1;
    double peak_h = 0.0;
    for (std::int64_t i : members) {  // largest |height|, first on ties
      if (std::isfinite(height[i]) && (peak < 0 || std::abs(height[i]) > std::abs(peak_h))) {
        peak = i;
        peak_h = height[i];
      }
    }
    if (peak < 0) peak = members.front();
    Candidate c;
    c.id = d.id;
    c.depth = d.peak_height;
    c.peak = peak;
    c.count = static_cast<int>(members.size());
    c.transform = tf_of(peak);
    const Rigid& g = tf[c.transform];
    Eigen::Vector3d n_scan = d.normal.allFinite() ? d.normal.normalized() : toward;
    if (n_scan.dot(toward) < 0.0) n_scan = -n_scan;
    c.normal = (g.R * n_scan).normalized();
    // Area: each member's cell spanned by its neighbours' half differences, projected on the
    // tangent plane; members without neighbours in both directions take point_area, or else the
    // mean of the others.
    areas.assign(members.size(), std::numeric_limits<double>::quiet_NaN());
    double area_sum = 0.0;
    int area_n = 0;
    for (std::size_t k = 0; k < members.size(); ++k) {
      const std::int64_t i = members[k];
      const std::ptrdiff_t r = i / cols, col = i % cols;
      const auto diff = [&](std::ptrdiff_t r0, std::ptrdiff_t c0, std::ptrdiff_t r1,
                            std::ptrdiff_t c1, Eigen::Vector3d* out) {
        const bool a = usable(r0, c0), b = usable(r1, c1);
        if (a && b) {
          *out = 0.5 * (base_at(r1 * cols + c1) - base_at(r0 * cols + c0));
        } else if (a || b) {
          *out = a ? Eigen::Vector3d(base_at(i) - base_at(r0 * cols + c0))
                   : Eigen::Vector3d(base_at(r1 * cols + c1) - base_at(i));
        } else {
          return false;
        }
        return true;
      };
      Eigen::Vector3d du, dv;
      if (p.point_area > 0.0) {
        areas[k] = p.point_area;
      } else if (diff(r, col - 1, r, col + 1, &du) && diff(r - 1, col, r + 1, col, &dv)) {
        areas[k] = std::abs(c.normal.dot(du.cross(dv)));
      }
      if (std::isfinite(areas[k])) {
        area_sum += areas[k];
        ++area_n;
      }
    }
    const double fill = area_n > 0 ? area_sum / area_n : 0.0;
    c.sum_base.setZero();
    c.sum_scan.setZero();
    for (std::size_t k = 0; k < members.size(); ++k) {
      const std::int64_t i = members[k];
      const double a = std::isfinite(areas[k]) ? areas[k] : fill;
      c.area += a;
      const double h = height[i];
      if (std::isfinite(h) && std::isfinite(c.depth) && (h > 0.0) == (c.depth > 0.0) && h != 0.0) {
        c.volume += std::abs(h) * a;
      }
      c.sum_base += base_at(i);
      c.sum_scan += scan_at(i);
    }
    if (c.area < p.min_area) {
      ++plan.rejected.size;
      continue;
    }
    const Eigen::Vector3d peak_scan = scan_at(peak);
    if ((roi_mask != nullptr && roi_mask[peak] == 0) ||
        (!p.roi_polygon.empty() && !inside_polygon(p.roi_polygon, peak_scan.x(), peak_scan.y()))) {
      ++plan.rejected.roi;
      continue;
    }
    if (p.anchor == TargetAnchor::kPeak) {
      c.anchor = base_at(peak);
      c.anchor_scan = peak_scan;
    } else {
      c.anchor = c.sum_base / c.count;
      c.anchor_scan = c.sum_scan / c.count;
    }
    if (p.edge_clearance > 0.0) {
      const double lim = p.edge_clearance * p.edge_clearance;
      const bool near = std::any_of(edge_pts.begin(), edge_pts.end(), [&](const auto& e) {
        return (e - c.anchor).squaredNorm() < lim;
      });
      if (near) {
        ++plan.rejected.edge;
        continue;
      }
    }
    cands.push_back(c);
  }
  plan.defects_used = static_cast<int>(cands.size());

  // Merge: connected components of "anchors closer than tool_radius" (single linkage).
  const int m = static_cast<int>(cands.size());
  std::vector<int> parent(static_cast<std::size_t>(m));
  std::iota(parent.begin(), parent.end(), 0);
  if (p.tool_radius > 0.0) {
    const double lim = p.tool_radius * p.tool_radius;
    for (int i = 0; i < m; ++i)
      for (int j = i + 1; j < m; ++j)
        if ((cands[i].anchor - cands[j].anchor).squaredNorm() < lim) {
          parent[find_root(parent, i)] = find_root(parent, j);
        }
  }
  std::vector<std::vector<int>> groups;
  std::vector<int> group_of(static_cast<std::size_t>(m), -1);
  for (int i = 0; i < m; ++i) {
    const int root = find_root(parent, i);
    if (group_of[root] < 0) {
      group_of[root] = static_cast<int>(groups.size());
      groups.emplace_back();
    }
    groups[group_of[root]].push_back(i);
  }
  std::vector<Target> targets;
  targets.reserve(groups.size());
  std::vector<Candidate> heads;
  for (const auto& grp : groups) {
    const Candidate* head = &cands[grp.front()];
    Target t;
    Eigen::Vector3d sum_base = Eigen::Vector3d::Zero(), sum_scan = Eigen::Vector3d::Zero();
    for (int k : grp) {
      const Candidate& c = cands[k];
      if (deeper(c, *head)) head = &c;
      t.area += c.area;
      t.volume += c.volume;
      t.count += c.count;
      t.defect_ids.push_back(c.id);
      sum_base += c.sum_base;
      sum_scan += c.sum_scan;
    }
    std::sort(t.defect_ids.begin(), t.defect_ids.end());
    t.depth = head->depth;
    t.peak_index = head->peak;
    t.normal = head->normal;
    if (p.anchor == TargetAnchor::kPeak) {
      t.point = head->anchor;
      t.point_scan = head->anchor_scan;
    } else {
      t.point = sum_base / t.count;
      t.point_scan = sum_scan / t.count;
    }
    const Eigen::Matrix3d& R_scan = tf[head->transform].R;
    const Eigen::Vector3d ref = p.x_reference.allFinite() ? p.x_reference : R_scan.col(1);
    t.rotation = tool_rotation(t.normal, ref, R_scan);
    t.position = t.point + p.standoff * t.normal;
    t.approach_point = t.position + p.approach * t.normal;
    t.retract_point = t.position + p.retract * t.normal;
    t.quaternion = quaternion_from_rotation(t.rotation);
    t.abc_deg = abc_from_rotation(t.rotation);
    targets.push_back(std::move(t));
    heads.push_back(*head);
  }
  // Deepest first, then the path.
  std::vector<int> rank(targets.size());
  std::iota(rank.begin(), rank.end(), 0);
  std::stable_sort(rank.begin(), rank.end(),
                   [&](int a, int b) { return deeper(heads[a], heads[b]); });
  std::vector<Eigen::Vector3d> pts;
  pts.reserve(rank.size());
  for (int k : rank) pts.push_back(targets[k].point);
  std::vector<int> order(rank.size());
  std::iota(order.begin(), order.end(), 0);
  if (p.order) order = order_path(pts, p.start);
  plan.path_length = path_length(pts, order, p.start);
  plan.targets.reserve(order.size());
  for (int k : order) plan.targets.push_back(std::move(targets[rank[k]]));
  return plan;
}

namespace nothrow {

template <typename T>
Status plan_targets(const GridView<T>& grid, const std::uint8_t* labels, const double* height,
                    const std::vector<Defect>& defects, const TransformsView& T_base_sensor,
                    const TargetParams& params, TargetPlan* out,
                    const std::uint8_t* roi_mask) noexcept {
  if (out == nullptr) return {StatusCode::kInvalidInput, "out: must not be null"};
  if (const char* msg = check_target_params(params)) {
    return {StatusCode::kInvalidParameter, msg};
  }
  if (grid.data == nullptr || grid.rows < 1 || grid.cols < 1) {
    return {StatusCode::kInvalidInput, "grid: must have at least one row and one column"};
  }
  if (labels == nullptr) return {StatusCode::kInvalidInput, "labels: must not be null"};
  if (height == nullptr) return {StatusCode::kInvalidInput, "height: must not be null"};
  if (const char* msg = check_transforms(T_base_sensor, grid.rows)) {
    return {StatusCode::kInvalidParameter, msg};
  }
  const std::int64_t n = static_cast<std::int64_t>(grid.rows) * grid.cols;
  for (const Defect& d : defects) {
    for (std::int64_t i : d.indices) {
      if (i < 0 || i >= n) {
        return {StatusCode::kInvalidInput, "defects: a point index is outside the grid"};
      }
    }
  }
  try {
    *out = miem::plan_targets(grid, labels, height, defects, T_base_sensor, params, roi_mask);
  } catch (const std::bad_alloc&) {
    return {StatusCode::kOutOfMemory, "out of memory"};
  } catch (...) {
    return {StatusCode::kInternal, "unexpected exception after the checks"};
  }
  return {};
}

template Status plan_targets<float>(const GridView<float>&, const std::uint8_t*, const double*,
                                    const std::vector<Defect>&, const TransformsView&,
                                    const TargetParams&, TargetPlan*,
                                    const std::uint8_t*) noexcept;
template Status plan_targets<double>(const GridView<double>&, const std::uint8_t*, const double*,
                                     const std::vector<Defect>&, const TransformsView&,
                                     const TargetParams&, TargetPlan*,
                                     const std::uint8_t*) noexcept;

}  // namespace nothrow

template TargetPlan plan_targets<float>(const GridView<float>&, const std::uint8_t*,
                                        const double*, const std::vector<Defect>&,
                                        const TransformsView&, const TargetParams&,
                                        const std::uint8_t*);
template TargetPlan plan_targets<double>(const GridView<double>&, const std::uint8_t*,
                                         const double*, const std::vector<Defect>&,
                                         const TransformsView&, const TargetParams&,
                                         const std::uint8_t*);

}  // namespace miem
