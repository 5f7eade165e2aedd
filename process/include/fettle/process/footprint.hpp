#pragma once
// A tool's solid at one pose, for what the verification and the cell's learned bias ask of the
// commanded paths: where the tool went (the swept footprint, grown by a margin) and how far a
// re-scanned point lies from the commanded tool's surface (docs/planning.md, "verify";
// docs/compensation.md).
#include <cstddef>

#include "fettle/config/part.hpp"
#include "fettle/core/geometry.hpp"

namespace fettle::process {

/// A tool's solid at one pose: a ball (its centre, radius) or a capped cylinder (its end face's
/// centre, the axis toward the spindle, radius, length; a disc's, and a cone's taken as one).
struct ToolSolid {
  Vec3 a = Vec3::Zero();     ///< a ball's centre; a cylinder's end-face centre (the tip)
  Vec3 axis = Vec3::UnitZ();  ///< tool z, from the tip toward the spindle
  double radius_mm = 0.0;
  double length_mm = 0.0;    ///< a cylinder's; 0 for a ball
  bool ball = false;

  /// The tool's solid at T_frame_tool (tool z from the tip toward the spindle), in that frame.
  static ToolSolid of(const config::Tool& tool, const Transform& T_frame_tool);
  /// Signed distance of q from the tool's surface (< 0 inside) and the surface's outward normal
  /// at the nearest place.
  [[nodiscard]] double distance(const Vec3& q, Vec3& normal) const;
  [[nodiscard]] double distance(const Vec3& q) const {
    Vec3 n;
    return distance(q, n);
  }
  /// The axis-aligned box holding the solid grown by grow_mm.
  [[nodiscard]] Vec3 box_min(double grow_mm) const;
  [[nodiscard]] Vec3 box_max(double grow_mm) const;
};

/// Where a tool went at one pose: every point within the margin of its solid. Not a capsule round
/// the axis: a 40 mm disc passing 15 mm over a face would hold that face under a capsule's 22 mm
/// half-sphere, and the face's measurement error beside a wall there read as a gouge where the
/// tool never came (test Footprint.ADiscPassingOverAFaceDoesNotHoldIt).
struct ToolVolume {
  ToolSolid solid;
  double margin_mm = 0.0;    ///< grown by this
  std::size_t region = 0;    ///< index into the recipe's regions

  static ToolVolume of(const config::Tool& tool, const Transform& T_frame_tool, double margin_mm, std::size_t region = 0);
  /// Whether q lies within the margin of the tool's solid.
  [[nodiscard]] bool contains(const Vec3& q) const { return solid.distance(q) <= margin_mm; }
  /// The axis-aligned box holding the grown volume.
  [[nodiscard]] Vec3 box_min() const { return solid.box_min(margin_mm); }
  [[nodiscard]] Vec3 box_max() const { return solid.box_max(margin_mm); }
};

}  // namespace fettle::process
