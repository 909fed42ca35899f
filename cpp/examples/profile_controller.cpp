// A cell-controller-style program: reads laser profiles from a file as if they came from a line
// scanner, streams them through miem::ProfileStream (no exceptions, no allocation per profile),
// groups the ABNORMAL points into defects as rows become final, and prints each defect.
//
//   profile_controller PROFILES.txt
//
// File format (text): '#' comments; "width N"; then one profile per line, N points as
// x y z x y z ... ("nan" marks a dropout).
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <optional>
#include <vector>

#include <miem/miem.hpp>
#include <miem/nothrow.hpp>
#include <miem/stream.hpp>

namespace {

// Reads the next profile line into `xyz` (3 * width floats); false at the end of the file.
bool read_profile(std::FILE* f, std::vector<char>& line, std::vector<float>& xyz, long width,
                  bool* ok) {
  *ok = true;
  while (std::fgets(line.data(), static_cast<int>(line.size()), f)) {
    if (line[0] == '#' || line[0] == '\n') continue;
    const char* p = line.data();
    char* end = nullptr;
    long n = 0;
    for (; n < 3 * width; ++n) {
      const float v = std::strtof(p, &end);
      if (end == p) break;
      xyz[static_cast<std::size_t>(n)] = v;
      p = end;
    }
    *ok = n == 3 * width;  // a short line: the profile is bad (pushed with its real size)
    if (!*ok) xyz.resize(static_cast<std::size_t>(n - n % 3));
    return true;
  }
  return false;
}

// 8-connected ABNORMAL cells across emitted rows, tracked row by row (union-find over cells of
// the previous and current row); a defect is printed once a row no longer touches it.
struct DefectTracker {
  struct Group {
    int parent;
    long count = 0;
    double sx = 0, sy = 0, sz = 0;
    long row0 = 0, row1 = 0, col0 = 0, col1 = 0;
    long seen = -1;  // last row that touched the group
    bool live = true;
  };
  std::vector<Group> groups;
  std::vector<int> prev, cur;  // group of each column in the previous / current row (-1: none)
  int printed = 0;

  explicit DefectTracker(long width)
      : prev(static_cast<std::size_t>(width), -1), cur(static_cast<std::size_t>(width), -1) {}

  int find(int g) {
    while (groups[static_cast<std::size_t>(g)].parent != g) {
      g = groups[static_cast<std::size_t>(g)].parent;
    }
    return g;
  }
  void unite(int a, int b) {
    a = find(a);
    b = find(b);
    if (a == b) return;
    Group& A = groups[static_cast<std::size_t>(a)];
    Group& B = groups[static_cast<std::size_t>(b)];
    B.parent = a;
    B.live = false;
    A.count += B.count;
    A.sx += B.sx;
    A.sy += B.sy;
    A.sz += B.sz;
    A.row0 = std::min(A.row0, B.row0);
    A.col0 = std::min(A.col0, B.col0);
    A.row1 = std::max(A.row1, B.row1);
    A.col1 = std::max(A.col1, B.col1);
  }

  void add_row(long row, const std::uint8_t* labels, const float* xyz) {
    const long W = static_cast<long>(cur.size());
    for (long c = 0; c < W; ++c) {
      cur[static_cast<std::size_t>(c)] = -1;
      if (labels[c] != miem::kAbnormal) continue;
      int g = -1;
      for (long dc = -1; dc <= 1; ++dc) {  // the previous row's three cells, then the left one
        const long cc = c + dc;
        if (cc < 0 || cc >= W || prev[static_cast<std::size_t>(cc)] < 0) continue;
        if (g < 0) g = find(prev[static_cast<std::size_t>(cc)]);
        else unite(g, prev[static_cast<std::size_t>(cc)]);
      }
      if (c > 0 && cur[static_cast<std::size_t>(c - 1)] >= 0) {
        if (g < 0) g = find(cur[static_cast<std::size_t>(c - 1)]);
        else unite(g, cur[static_cast<std::size_t>(c - 1)]);
      }
      if (g < 0) {
        g = static_cast<int>(groups.size());
        Group ng;
        ng.parent = g;
        ng.row0 = ng.row1 = row;
        ng.col0 = ng.col1 = c;
        groups.push_back(ng);
      }
      g = find(g);
      Group& G = groups[static_cast<std::size_t>(g)];
      G.count += 1;
      G.sx += xyz[3 * c];
      G.sy += xyz[3 * c + 1];
      G.sz += xyz[3 * c + 2];
      G.row1 = std::max(G.row1, row);
      G.col0 = std::min(G.col0, c);
      G.col1 = std::max(G.col1, c);
      cur[static_cast<std::size_t>(c)] = g;
    }
    // Groups of the previous row that this row does not touch are finished.
    for (long c = 0; c < W; ++c)
      if (cur[static_cast<std::size_t>(c)] >= 0)
        groups[static_cast<std::size_t>(find(cur[static_cast<std::size_t>(c)]))].seen = row;
    for (long c = 0; c < W; ++c) {
      const int p = prev[static_cast<std::size_t>(c)];
      if (p >= 0 && groups[static_cast<std::size_t>(find(p))].seen != row) close(find(p));
    }
    prev.swap(cur);
  }

  void close(int g) {
    Group& G = groups[static_cast<std::size_t>(g)];
    if (!G.live) return;
    G.live = false;
    const double n = static_cast<double>(G.count);
    std::printf("defect %d: rows %ld-%ld cols %ld-%ld points %ld centroid %.3f %.3f %.3f\n",
                printed++, G.row0, G.row1, G.col0, G.col1, G.count, G.sx / n, G.sy / n, G.sz / n);
  }

  void finish() {
    for (long c = 0; c < static_cast<long>(prev.size()); ++c)
      if (prev[static_cast<std::size_t>(c)] >= 0) close(find(prev[static_cast<std::size_t>(c)]));
  }
};

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s PROFILES.txt\n", argv[0]);
    return 2;
  }
  std::FILE* f = std::fopen(argv[1], "r");
  if (!f) {
    std::fprintf(stderr, "cannot open %s\n", argv[1]);
    return 2;
  }
  std::vector<char> line(1 << 22);
  long width = 0;
  while (width == 0 && std::fgets(line.data(), static_cast<int>(line.size()), f)) {
    if (std::strncmp(line.data(), "width", 5) == 0) {
      width = std::strtol(line.data() + 5, nullptr, 10);
    }
  }
  if (width < 1) {
    std::fprintf(stderr, "%s: no 'width N' line\n", argv[1]);
    return 2;
  }

  // The stream's default: the whole recommended detector (angle, height and edge tests,
  // min_step "auto", heights, defects); a push splits its column work among all cores
  // (params.num_threads = 0; set 1 to keep the stream on this thread).
  const miem::DetectParams params = miem::stream_default_params();
  std::optional<miem::ProfileStream<float>> stream;
  const miem::Status made = miem::nothrow::make_stream(width, params, &stream);
  if (!made.ok()) {
    std::fprintf(stderr, "cannot start the stream: %s\n", made.message);
    return 1;
  }
  std::printf("miem %s: width %ld, lag %d profiles\n", miem::version(), width, stream->lag());

  // The controller keeps the last lag + 1 profiles to map labels back to points.
  const long keep = stream->lag() + 1;
  std::vector<float> ring(static_cast<std::size_t>(keep * 3 * width));
  std::vector<float> xyz(static_cast<std::size_t>(3 * width));
  DefectTracker defects(width);
  long pushed = 0, rejected = 0, abnormal = 0;
  auto take = [&](const miem::StreamRow& row) {
    const float* pts = ring.data() + (row.index % keep) * 3 * width;
    for (long c = 0; c < width; ++c) abnormal += row.labels[c] == miem::kAbnormal;
    defects.add_row(static_cast<long>(row.index), row.labels, pts);
  };

  bool ok = true;
  miem::StreamRow row;
  while (read_profile(f, line, xyz, width, &ok)) {
    const miem::Status st =
        stream->push(xyz.data(), static_cast<std::ptrdiff_t>(xyz.size() / 3), &row);
    if (st.code == miem::StatusCode::kWrongWidth || st.code == miem::StatusCode::kInvalidInput) {
      std::fprintf(stderr, "profile %ld rejected: %s\n", pushed + rejected, st.message);
      ++rejected;
      xyz.assign(static_cast<std::size_t>(3 * width), 0.0f);
      continue;
    }
    if (!st.ok()) std::fprintf(stderr, "profile %ld: %s\n", pushed, st.message);
    std::memcpy(ring.data() + (pushed % keep) * 3 * width, xyz.data(),
                static_cast<std::size_t>(3 * width) * sizeof(float));
    ++pushed;
    if (row.ready()) take(row);
  }
  std::fclose(f);
  while (stream->flush(&row)) take(row);
  defects.finish();
  std::printf("profiles %ld, rejected %ld, abnormal points %ld, defects %d\n", pushed, rejected,
              abnormal, defects.printed);
  return 0;
}
