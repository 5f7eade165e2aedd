#pragma once
// Random draws in a fixed order. C++ leaves the order in which a call's arguments (and most
// operands) are evaluated unspecified: Vec3(u(rng), u(rng), u(rng)) is drawn right to left by
// gcc and left to right by clang, so a test written that way sees different data under the
// sanitizer builds (clang) than under `make test` (gcc). These helpers draw last to first, the
// order gcc uses, so the data the tests' expectations are measured on is the same everywhere.
#include <array>
#include <cstddef>

namespace fettle::test {

/// N draws of `d`, the last one first: draws<3>(u, rng) holds the arguments gcc passed for
/// f(u(rng), u(rng), u(rng)). (A braced list {u(rng), ...} is drawn left to right by every compiler.)
template <std::size_t N, class Dist, class Rng>
std::array<typename Dist::result_type, N> draws(Dist& d, Rng& rng) {
  std::array<typename Dist::result_type, N> a{};
  for (std::size_t i = N; i-- > 0;) a[i] = d(rng);
  return a;
}

/// V(d(rng), d(rng), d(rng)) drawn in gcc's order.
template <class V, class Dist, class Rng>
V draw3(Dist& d, Rng& rng) {
  const auto a = draws<3>(d, rng);
  return V(a[0], a[1], a[2]);
}

/// V(d(rng), d(rng)) drawn in gcc's order.
template <class V, class Dist, class Rng>
V draw2(Dist& d, Rng& rng) {
  const auto a = draws<2>(d, rng);
  return V(a[0], a[1]);
}

}  // namespace fettle::test
