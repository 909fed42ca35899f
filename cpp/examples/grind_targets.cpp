// A cell-controller-style program: detect defects in a scan (no exceptions), plan grinding
// targets in the robot's base frame with miem::nothrow::plan_targets, and print each target as an
// ABB robtarget (mm, quaternion w first) and KUKA E6POS angles.
//
//   grind_targets PROFILES.txt [X Y Z]      (the sensor's position in the base frame, mm)
//
// PROFILES.txt is profile_controller's format: "width N", then one profile per line.
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <vector>

#include <miem/miem.hpp>
#include <miem/nothrow.hpp>
#include <miem/targets.hpp>

int main(int argc, char** argv) {
  if (argc != 2 && argc != 5) {
    std::fprintf(stderr, "usage: %s PROFILES.txt [X Y Z]\n", argv[0]);
    return 2;
  }
  std::FILE* f = std::fopen(argv[1], "r");
  if (f == nullptr) {
    std::fprintf(stderr, "cannot open %s\n", argv[1]);
    return 1;
  }
  long width = 0;
  std::vector<char> line(1 << 20);
  std::vector<float> xyz;
  long rows = 0;
  while (std::fgets(line.data(), static_cast<int>(line.size()), f)) {
    if (line[0] == '#' || line[0] == '\n') continue;
    if (width == 0) {
      if (std::sscanf(line.data(), "width %ld", &width) != 1 || width < 1) {
        std::fprintf(stderr, "expected 'width N'\n");
        return 1;
      }
      continue;
    }
    std::vector<float> row;
    const char* p = line.data();
    char* end = nullptr;
    for (float v = std::strtof(p, &end); end != p; v = std::strtof(p, &end)) {
      row.push_back(v);
      p = end;
    }
    if (static_cast<long>(row.size()) != 3 * width) continue;  // a bad profile: skipped
    xyz.insert(xyz.end(), row.begin(), row.end());
    ++rows;
  }
  std::fclose(f);

  std::optional<miem::OrganizedDetector> det;
  miem::DetectParams params;
  params.scales = {1, 2};  // as profile_controller: also defects two points wide
  miem::Status st = miem::nothrow::make_detector(params, &det);
  const auto grid = miem::GridView<float>::dense(xyz.data(), rows, width);
  std::vector<std::uint8_t> labels(static_cast<std::size_t>(rows * width));
  std::vector<double> height(labels.size());
  miem::OrganizedOutput out{labels.data(), nullptr, nullptr, height.data()};
  miem::DetectSummary summary;
  if (st.ok()) st = miem::nothrow::detect(*det, grid, out, &summary);
  if (!st.ok()) {
    std::fprintf(stderr, "detect: %s\n", st.message);
    return 1;
  }

  // Sensor looking down from (X, Y, Z), its x axis along the base y axis.
  const double tx = argc == 5 ? std::atof(argv[2]) : 850.0;
  const double ty = argc == 5 ? std::atof(argv[3]) : -120.0;
  const double tz = argc == 5 ? std::atof(argv[4]) : 310.0;
  const double T[16] = {0, -1, 0, tx, 1, 0, 0, ty, 0, 0, 1, tz, 0, 0, 0, 1};
  miem::TargetParams tp;
  tp.tool_radius = 3.0;
  tp.approach = 25.0;
  miem::TargetPlan plan;
  st = miem::nothrow::plan_targets(grid, labels.data(), height.data(), summary.defects, {T, 1},
                                   tp, &plan);
  if (!st.ok()) {
    std::fprintf(stderr, "plan_targets: %s\n", st.message);
    return 1;
  }
  std::printf("defects %d, targets %zu, path %.1f mm\n", plan.defects_in, plan.targets.size(),
              plan.path_length);
  for (std::size_t k = 0; k < plan.targets.size(); ++k) {
    const miem::Target& t = plan.targets[k];
    std::printf("CONST robtarget pT%zu:=[[%.3f,%.3f,%.3f],[%.6f,%.6f,%.6f,%.6f],[0,0,0,0],"
                "[9E9,9E9,9E9,9E9,9E9,9E9]]; ! depth %.3f, A %.2f B %.2f C %.2f\n",
                k + 1, t.position.x(), t.position.y(), t.position.z(), t.quaternion(0),
                t.quaternion(1), t.quaternion(2), t.quaternion(3), t.depth, t.abc_deg(0),
                t.abc_deg(1), t.abc_deg(2));
  }
  // A scaled transform is refused with a status naming it, not an exception.
  const double bad[16] = {2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1};
  st = miem::nothrow::plan_targets(grid, labels.data(), height.data(), summary.defects, {bad, 1},
                                   tp, &plan);
  std::printf("scaled transform: %s\n", st.message);
  return 0;
}
