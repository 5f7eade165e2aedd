#pragma once
// Whether a point lies in a recipe region's ROI box (part frame).
#include <cmath>
#include <cstddef>

#include "fettle/config/part.hpp"

namespace fettle::config {

/// Whether a part-frame point (anything indexable [0..2]: Eigen vectors) lies inside the
/// region's ROI box, grown by grow_mm on every side.
template <class Point>
[[nodiscard]] bool roi_contains(const Region& region, const Point& p_part, double grow_mm = 0.0) {
  for (std::size_t k = 0; k < 3; ++k)
    if (std::abs(static_cast<double>(p_part[static_cast<int>(k)]) - region.roi_center_mm[k]) >
        0.5 * region.roi_size_mm[k] + grow_mm)
      return false;
  return true;
}

}  // namespace fettle::config
