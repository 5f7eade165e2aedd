// The simulator's error budget file ([errors], fettle/config/errors.hpp); loaded by load.cpp.
#include "fettle/config/errors.hpp"

#include "sections.hpp"

namespace fettle::config::detail {

void read_errors(TableReader& root, ErrorBudget& e) {
  if (auto t = root.table("errors", Need::required)) {
    t->number("hand_eye_mm", e.hand_eye_mm, {0.0, 10.0});
    t->number("hand_eye_deg", e.hand_eye_deg, {0.0, 5.0});
    t->choice("hand_eye_pivot", e.hand_eye_pivot, {"fixture", "camera"});
    t->number("slide_repeatability_mm", e.slide_repeatability_mm, {0.0, 5.0});
    t->number("intrinsics_focal_pct", e.intrinsics_focal_pct, {0.0, 5.0});
    t->number("intrinsics_center_px", e.intrinsics_center_px, {0.0, 50.0});
    t->number("path_noise_mm", e.path_noise_mm, {0.0, 5.0});
    t->number("path_bias_mm", e.path_bias_mm, {0.0, 5.0});
    t->number("tcp_length_mm", e.tcp_length_mm, {-5.0, 5.0});
    t->number("depth_noise_mm", e.depth_noise_mm, {0.0, 5.0});
    t->number("depth_correlated_mm", e.depth_correlated_mm, {0.0, 5.0});
    t->number("depth_correlation_px", e.depth_correlation_px, {0.0, 2000.0});
    t->number("interreflection_mm", e.interreflection_mm, {0.0, 5.0});
    if (t->has("form_deviation_mm")) {
      double f = 0.0;
      t->number("form_deviation_mm", f, {0.0, 5.0});
      e.form_deviation_mm = f;
    }
    t->number("wheel_wear_mm_per_cm3", e.wheel_wear_mm_per_cm3, {0.0, 1.0});
    t->number("wheel_wear_spread_pct", e.wheel_wear_spread_pct, {0.0, 100.0});
    t->number("wheel_worn_start_mm", e.wheel_worn_start_mm, {0.0, 5.0});
    if (e.depth_correlated_mm > 0.0 && !(e.depth_correlation_px > 0.0))
      t->error("depth_correlation_px", "must be above 0 when depth_correlated_mm is set");
    if (e.interreflection_mm > 0.0)
      t->error("interreflection_mm", "is not modelled by the simulator yet: leave it 0 (issue 34)");
  }
}

}  // namespace fettle::config::detail
