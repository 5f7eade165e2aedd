#pragma once
// Where a tool went: its volume at one pose, grown by a margin, for the verification's swept
// footprint (docs/planning.md, "verify"). A place the tool's grown volume never held cannot have
// been cut, and the verification does not judge it as a gouge.
#include <cstddef>

#include "fettle/config/part.hpp"
#include "fettle/core/geometry.hpp"

namespace fettle::process {

/// A tool's volume at one pose, grown by a margin: a ball's sphere, or a cylinder's (a disc's, a
/// cone's taken as a cylinder) with its flat end and its rounded-off rim, i.e. every point within
/// the margin of the tool's solid. Not a capsule: a 40 mm disc passing 15 mm over a face would
/// hold that face under a capsule's 22 mm half-sphere, and the face's measurement error beside a
/// wall there read as a gouge where the tool never came (test
/// Footprint.ADiscPassingOverAFaceDoesNotHoldIt).
struct ToolVolume {
  Vec3 a = Vec3::Zero();     ///< a ball's centre; a cylinder's end-face centre (the tip)
  Vec3 b = Vec3::Zero();     ///< a cylinder's other end on its axis (a ball: == a)
  double radius_mm = 0.0;    ///< the tool's radius
  double margin_mm = 0.0;    ///< grown by this
  bool ball = false;         ///< a sphere of radius_mm about a
  std::size_t region = 0;    ///< index into the recipe's regions

  /// The tool's volume at T_frame_tool (tool z from the tip toward the spindle), in that frame.
  static ToolVolume of(const config::Tool& tool, const Transform& T_frame_tool, double margin_mm, std::size_t region = 0);
  /// Whether q lies within the margin of the tool's solid.
  [[nodiscard]] bool contains(const Vec3& q) const;
  /// The axis-aligned box holding the grown volume.
  [[nodiscard]] Vec3 box_min() const { return a.cwiseMin(b) - Vec3::Constant(radius_mm + margin_mm); }
  [[nodiscard]] Vec3 box_max() const { return a.cwiseMax(b) + Vec3::Constant(radius_mm + margin_mm); }
};

}  // namespace fettle::process
