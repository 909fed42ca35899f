// Plane fits from centred, block-merged moments: one pass over memory, double accumulation,
// deterministic for any thread count.
#include "miem/plane.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Eigenvalues>

#include "parallel.hpp"
#include "plane_math.hpp"

namespace miem {

namespace {

constexpr std::ptrdiff_t kBlock = 4096;  // points per block: stays in L1/L2 for the second pass

template <typename T>
Moments block_moments(const PointsView<T>& pts, std::ptrdiff_t begin, std::ptrdiff_t end) {
  // Second pass over the (cached) block, centred on its own mean.
  return detail::two_pass_moments(
      begin, end, [&](std::ptrdiff_t i) { return pts[i]; },
      [&](std::ptrdiff_t i) { return pts[i].allFinite(); });
}

}  // namespace

void Moments::merge(const Moments& other) {
  if (other.n == 0) return;
  if (n == 0) {
    *this = other;
    return;
  }
  const double na = static_cast<double>(n), nb = static_cast<double>(other.n);
  const double nt = na + nb;
  const Eigen::Vector3d delta = other.mean - mean;
  mean += delta * (nb / nt);
  scatter += other.scatter + (delta * delta.transpose()) * (na * nb / nt);
  n += other.n;
}

const char* to_string(PlaneStatus status) noexcept {
  switch (status) {
    case PlaneStatus::kOk:
      return "ok";
    case PlaneStatus::kTooFewPoints:
      return "fewer than 3 finite points";
    case PlaneStatus::kDegenerate:
      return "degenerate points (all equal or collinear)";
  }
  return "unknown";
}

Eigen::Vector3d orient_normal(const Eigen::Vector3d& n) noexcept {
  return n * detail::orient_sign(n.x(), n.y(), n.z());
}

PlaneStatus eigen_plane_from_moments(const Moments& m, Plane* out) noexcept {
  if (m.n < 3) return PlaneStatus::kTooFewPoints;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(m.scatter, Eigen::ComputeEigenvectors);
  if (es.info() != Eigen::Success) return PlaneStatus::kDegenerate;
  const Eigen::Vector3d ev = es.eigenvalues();
  if (!(ev(2) > 0.0) || ev(1) <= 1e-12 * ev(2)) return PlaneStatus::kDegenerate;
  Plane p;
  p.normal = orient_normal(es.eigenvectors().col(0).normalized());
  p.centroid = m.mean;
  p.d = -p.normal.dot(m.mean);
  p.rms = std::sqrt(std::max(ev(0), 0.0) / static_cast<double>(m.n));
  p.n_points = m.n;
  p.eigenvalues = ev;
  *out = p;
  return PlaneStatus::kOk;
}

PlaneStatus lstsq_plane_from_moments(const Moments& m, Plane* out) noexcept {
  if (m.n < 3) return PlaneStatus::kTooFewPoints;
  const Eigen::Matrix3d& s = m.scatter;
  const double sxx = s(0, 0), sxy = s(0, 1), syy = s(1, 1);
  const double det = sxx * syy - sxy * sxy;
  if (!(sxx * syy > 0.0) || det <= 1e-12 * (sxx * syy)) return PlaneStatus::kDegenerate;
  const double a = (s(0, 2) * syy - s(1, 2) * sxy) / det;
  const double b = (s(1, 2) * sxx - s(0, 2) * sxy) / det;
  Plane p;
  p.normal = Eigen::Vector3d(-a, -b, 1.0).normalized();
  p.centroid = m.mean;
  p.d = -p.normal.dot(m.mean);
  const double ss = p.normal.dot(s * p.normal);  // sum of squared orthogonal distances
  p.rms = std::sqrt(std::max(ss, 0.0) / static_cast<double>(m.n));
  p.n_points = m.n;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(s, Eigen::EigenvaluesOnly);
  p.eigenvalues = es.eigenvalues();
  *out = p;
  return PlaneStatus::kOk;
}

template <typename T>
Moments compute_moments(const PointsView<T>& points, int num_threads) {
  const std::ptrdiff_t n = points.size;
  const std::ptrdiff_t nblocks = (n + kBlock - 1) / kBlock;
  if (nblocks <= 1) return block_moments(points, 0, n);
  std::vector<Moments> blocks(static_cast<std::size_t>(nblocks));
  const int nt = detail::thread_count(num_threads, n);
#pragma omp parallel for schedule(static) num_threads(nt) if (nt > 1)
  for (std::ptrdiff_t b = 0; b < nblocks; ++b) {
    blocks[b] = block_moments(points, b * kBlock, std::min(n, (b + 1) * kBlock));
  }
  // Fixed merge order (pairwise tree) -> identical result whatever the thread count.
  for (std::ptrdiff_t width = 1; width < nblocks; width *= 2) {
    for (std::ptrdiff_t b = 0; b + width < nblocks; b += 2 * width) blocks[b].merge(blocks[b + width]);
  }
  return blocks[0];
}

namespace {
template <typename T>
void check_view(const PointsView<T>& points) {
  if (points.size < 0 || (points.size > 0 && points.data == nullptr)) {
    throw std::invalid_argument("points: null data");
  }
}
}  // namespace

template <typename T>
Plane fit_plane_eigen(const PointsView<T>& points, int num_threads) {
  check_view(points);
  Plane p;
  const PlaneStatus st = eigen_plane_from_moments(compute_moments(points, num_threads), &p);
  if (st != PlaneStatus::kOk) {
    throw std::invalid_argument(std::string("points: cannot fit a plane: ") + to_string(st));
  }
  return p;
}

template <typename T>
Plane fit_plane_lstsq(const PointsView<T>& points, int num_threads) {
  check_view(points);
  Plane p;
  const PlaneStatus st = lstsq_plane_from_moments(compute_moments(points, num_threads), &p);
  if (st == PlaneStatus::kDegenerate) {
    throw std::invalid_argument(
        "points: cannot fit z = ax + by + c: the x, y coordinates are collinear or equal");
  }
  if (st != PlaneStatus::kOk) {
    throw std::invalid_argument(std::string("points: cannot fit a plane: ") + to_string(st));
  }
  return p;
}

template Moments compute_moments<float>(const PointsView<float>&, int);
template Moments compute_moments<double>(const PointsView<double>&, int);
template Plane fit_plane_eigen<float>(const PointsView<float>&, int);
template Plane fit_plane_eigen<double>(const PointsView<double>&, int);
template Plane fit_plane_lstsq<float>(const PointsView<float>&, int);
template Plane fit_plane_lstsq<double>(const PointsView<double>&, int);

const char* version() noexcept { return MIEM_VERSION_STRING; }

int max_threads() noexcept { return detail::max_threads(); }

}  // namespace miem
