#pragma once
// A part recipe (config/parts/*.toml): what the part is, where it sits, its regions
// and how each is ground.
#include <array>
#include <filesystem>
#include <string>
#include <vector>

#include "fettle/config/geometry.hpp"
#include "fettle/config/vision.hpp"

namespace fettle::config {

enum class RegionType { ring_flash, riser, straight_flash, circle_flash };
enum class ToolShape { cylinder, ball, cone };
/// How a ring / circle flash is ground: `chamfer` = the paper's Eqs. 17-21 (tool axis at
/// chamfer_deg from the parting plane, for a flash at an edge); `periphery` = the side of a
/// cylindrical tool (axis along the parting plane normal) runs against the wall the fin
/// stands out of, grinding it flush (a fin below the top of a flange or boss).
enum class FlashContact { chamfer, periphery };
/// Where a region's pose comes from: its own fine ICP on the region's template, or the whole
/// part's (for a region whose visible surface does not fix it sideways, e.g. a flange wall the
/// camera sees only at grazing angles).
enum class RegionPose { region, part };

const char* to_string(RegionType type);
const char* to_string(ToolShape shape);

struct Tool {
  std::string name;
  ToolShape shape = ToolShape::cylinder;
  double diameter_mm = 50.0;
  double length_mm = 10.0;
  double cone_angle_deg = 0.0;                  ///< cone tools only
  std::array<double, 3> tcp_mm{0.0, 0.0, 0.0};  ///< TCP in the flange frame
  /// The wheel's stated wear: its radius shrinks this much per cm3 of iron it removes (from its
  /// maker's G-ratio; 0: not stated). The cell predicts each wheel's wear from the volume it
  /// removed at this rate until its cut shows the wheel's radius, then at the rate it measured
  /// (process::CellBias, docs/compensation.md).
  double wear_mm_per_cm3 = 0.0;
  /// How far one wheel's own rate may lie from the stated one, either way: the cell plans with
  /// the least wear and asks for a new wheel at the most until it has measured the wheel's rate.
  double wear_tolerance_pct = 30.0;
  /// The wheel's life: the cell asks for a new wheel when it predicts more radius lost than this
  /// (0: no limit).
  double max_wear_mm = 0.0;
};

struct Region {
  std::string name;
  RegionType type = RegionType::ring_flash;
  std::string tool;                               ///< name of a [[tools]] entry
  std::array<double, 3> roi_center_mm{0, 0, 0};   ///< ROI box centre in the part frame
  std::array<double, 3> roi_size_mm{10, 10, 10};  ///< ROI box edge lengths
  double feed_mm_s = 20.0;
  double spindle_rpm = 6000.0;
  double excess_threshold_mm = 0.2;  ///< material higher than this above the template is excess
  double allowance_mm = 0.05;        ///< left above the template by the last pass
  RegionPose pose = RegionPose::region;
  // ring_flash / circle_flash
  double chamfer_deg = 45.0;
  double point_spacing_mm = 1.0;
  double overlap_mm = 5.0;
  FlashContact contact = FlashContact::chamfer;
  // riser
  double depth_per_pass_mm = 1.0;
  double stepover_mm = 5.0;
  double margin_mm = 3.0;
  // straight_flash
  int passes = 1;
};

struct FixturePrior {
  std::array<double, 3> position_mm{0, 0, 0};   ///< nominal part origin in the fixture frame
  std::array<double, 3> rotation_deg{0, 0, 0};  ///< nominal part rotation (roll, pitch, yaw)
  double position_tolerance_mm = 5.0;           ///< how far the real part may be from nominal
  double rotation_tolerance_deg = 5.0;
};

struct TemplateSource {
  std::string kind = "simulator";  ///< simulator (the simulator's golden part) | scan
  std::filesystem::path scan;      ///< golden scan (PLY/PCD); kind simulator: optional, where fettle-sim golden writes it
  double voxel_mm = 0.5;
};

/// [verification]: the verdict of the scan after grinding, per region (fettle::daemon::verify).
struct VerificationSettings {
  /// The levels the shares count against (Zhu et al.'s Table 2: points more than 0.3 / 0.5 mm off
  /// the template). The planner's wear slack (process::wear_slack_mm) keeps under the first.
  static constexpr double kShareLevelMm = 0.3;
  static constexpr double kStrictShareLevelMm = 0.5;
  double ok_max_share_over_0_3_pct = 1.0;  ///< OK needs at most this share of ROI points > 0.3 mm off
  double ok_max_share_over_0_5_pct = 0.1;  ///< ... and at most this share > 0.5 mm off
  double gouge_depth_mm = 0.3;             ///< a point this far below the template is gouged ...
  double nok_max_share_gouged_pct = 0.1;   ///< ... and more gouged ROI points than this share: NOK
  double max_regrind_height_mm = 5.0;      ///< more material than this left above the template: NOK
  /// Flying pixels of the re-scan: drop a pixel whose range jumps more than this to a neighbour
  /// (as vision.jump_edge_mm, for the verification only); 0 = off.
  double jump_edge_mm = 0.0;
  /// Gouges are looked for in every ROI and wherever the tool went: within the tool's radius
  /// plus this of every uploaded pose and move (the swept footprint).
  double footprint_margin_mm = 2.0;
  /// A gouge is confirmed by the re-scan points within this radius of it: their median lies
  /// more than gouge_depth_mm below the template (one noisy point is not a gouge).
  double gouge_confirm_radius_mm = 1.0;
};

struct PartRecipe {
  std::filesystem::path source;
  std::string id;
  std::string description;
  TemplateSource template_source;
  FixturePrior fixture;
  std::vector<Tool> tools;
  std::vector<Region> regions;
  PartGeometry geometry;
  VisionSettings vision;
  VerificationSettings verification;
};

}  // namespace fettle::config
