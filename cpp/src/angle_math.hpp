// Branch-free angle arithmetic for the vectorized kernels: the flag test and the running
// maximum of cos(theta) without square roots, and an acos that vectorizes.
#pragma once

#include <cmath>

namespace miem::detail {

/// acos(x) for x in [-1, 1], radians; |error| < 4e-16. Branch-free (vectorizes), unlike libm's.
/// asin(s) = s + s z R(z) with z = s^2 <= 1/4; R is a degree-12 fit (Chebyshev nodes, 50
/// digits) of (asin(sqrt z)/sqrt z - 1)/z on [0, 1/4], max error 1.5e-17.
inline double acos_fast(double x) {
  constexpr double kPi = 3.141592653589793238462643;
  constexpr double kHalfPi = 1.570796326794896619231322;
  const double ax = std::fabs(x);
  const bool big = ax > 0.5;
  const double z = big ? (1.0 - ax) * 0.5 : ax * ax;
  const double s = big ? std::sqrt(z) : ax;
  double r = 0.028757851367421564708;
  r = r * z - 0.014851887071247203224;
  r = r * z + 0.017400879442694022443;
  r = r * z + 0.0054575067186403583004;
  r = r * z + 0.010322814350185779287;
  r = r * z + 0.011479177415184905896;
  r = r * z + 0.013971212973552933304;
  r = r * z + 0.017352392720869972942;
  r = r * z + 0.022372172942149887875;
  r = r * z + 0.030381944138531247287;
  r = r * z + 0.044642857146355429783;
  r = r * z + 0.074999999999984329332;
  r = r * z + 0.16666666666666667827;
  const double as = s + s * z * r;  // asin(s)
  const double a = big ? 2.0 * as : kHalfPi - as;  // acos(|x|)
  return x < 0.0 ? kPi - a : a;
}

/// cos(theta) >= cos0 for cos(theta) = uv / sqrt(prod), prod > 0, without the square root.
/// c2 = cos0 * cos0.
inline bool cos_at_least(double uv, double prod, double cos0, double c2) {
  return cos0 >= 0.0 ? (uv >= 0.0) & (uv * uv >= c2 * prod) : (uv >= 0.0) | (uv * uv <= c2 * prod);
}

}  // namespace miem::detail
