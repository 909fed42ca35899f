// The coordinate-range scan (largest_finite_magnitude, miem/views.hpp): values by hand.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <vector>

#include "miem/views.hpp"

namespace {

TEST(CoordinateRange, LargestFiniteMagnitudeSkipsNonFiniteValues) {
  const double inf = std::numeric_limits<double>::infinity();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  // 2 rows of 5, row stride 8: the values between the rows (-100) are not part of the block
  const std::vector<double> a = {1.0, -inf, nan, -2.5, 0.5, -100, -100, -100,
                                 -0.0, 2.0, inf, -3.25, nan, -100, -100, -100};
  EXPECT_EQ(miem::largest_finite_magnitude(a.data(), 2, 5, 8, 1), 3.25);
  EXPECT_EQ(miem::largest_finite_magnitude(a.data(), 1, 16, 0, 1), 100.0);
  // every other value of the first row: 1, nan, 0.5
  EXPECT_EQ(miem::largest_finite_magnitude(a.data(), 1, 3, 0, 2), 1.0);
  // a reversed column: a[8], a[0] (negative row stride)
  EXPECT_EQ(miem::largest_finite_magnitude(a.data() + 8, 2, 1, -8, 1), 1.0);
  const std::vector<double> none = {nan, inf, -inf, -0.0};
  EXPECT_EQ(miem::largest_finite_magnitude(none.data(), 1, 4, 0, 1), 0.0);
  EXPECT_EQ(miem::largest_finite_magnitude(none.data(), 0, 4, 0, 1), 0.0);
  const std::vector<float> f = {1e-30f, -3e38f, std::numeric_limits<float>::infinity(), 2.0f};
  EXPECT_EQ(miem::largest_finite_magnitude(f.data(), 1, 4, 0, 1), static_cast<double>(3e38f));
  // long rows: the last value (past the vector part), then one inside it (an odd lane), between
  // infinities and NaNs in every lane
  std::vector<double> row(1003, 1.0);
  for (std::size_t i = 0; i < row.size(); i += 5) row[i] = i % 2 ? inf : nan;
  row.back() = -9.0;
  EXPECT_EQ(miem::largest_finite_magnitude(row.data(), 1, 1003, 0, 1), 9.0);
  row[501] = -20.0;
  EXPECT_EQ(miem::largest_finite_magnitude(row.data(), 1, 1003, 0, 1), 20.0);
  std::vector<float> frow(21, -1.0f);
  frow[3] = -std::numeric_limits<float>::infinity();
  frow[13] = -7.5f;
  frow[20] = 5.0f;
  EXPECT_EQ(miem::largest_finite_magnitude(frow.data(), 1, 21, 0, 1), 7.5);
}

}  // namespace
