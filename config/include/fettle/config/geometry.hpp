#pragma once
// The part's parametric geometry ([geometry] in a part recipe), used by the simulator
// to build the casting and its golden template. Everything is in the part frame
// (millimetres, z up, the part's bottom on z = 0); see docs/simulator.md.
//
// The body is a union of blocks (boxes whose top face may be tilted) and cylinders
// (the flange, bosses). Removable material (flash, risers) is attached to features;
// each feature names the recipe region it belongs to (`region`), which is how the
// simulator's ground truth is reported per region. Ranges are [min, max]: every
// casting draws its own value from them with its seed.
#include <array>
#include <string>
#include <vector>

namespace fettle::config {

/// A [min, max] range a casting draws a value from.
struct ValueRange {
  double min = 0.0;
  double max = 0.0;
};

/// A box from min_mm to max_mm; its top face may be tilted by top_slope_deg
/// (slope along x, along y) about the top's centre.
struct BodyBlock {
  std::array<double, 3> min_mm{0, 0, 0};
  std::array<double, 3> max_mm{10, 10, 10};
  std::array<double, 2> top_slope_deg{0, 0};
};

/// A vertical cylinder of the body (e.g. the flange) from base_z to top_z.
struct BodyCylinder {
  std::array<double, 2> center_mm{0, 0};
  double radius_mm = 10.0;
  double base_z_mm = 0.0;
  double top_z_mm = 10.0;
};

/// A ring parting-line flash: a thin horizontal fin around a cylinder of the body.
struct RingFlash {
  std::string region;              ///< recipe region name
  BodyCylinder cylinder;           ///< the flange (or boss) the fin surrounds (part of the body)
  double parting_z_mm = 5.0;       ///< height of the fin's mid-plane
  ValueRange thickness_mm{0.3, 1.5};
  ValueRange extent_mm{1.0, 4.0};  ///< radial extent beyond the cylinder
  double edge_irregularity_mm = 0.4;  ///< amplitude of the fin edge's wobble
  double gap_fraction = 0.1;          ///< fraction of the circumference without fin
};

/// A pouring riser stub standing on a body face; the broken top is tilted and rough.
struct Riser {
  std::string region;
  std::array<double, 2> center_mm{0, 0};
  ValueRange diameter_mm{20.0, 40.0};
  ValueRange height_mm{3.0, 15.0};  ///< above the face, at the centre
  ValueRange top_tilt_deg{0.0, 10.0};
  double roughness_mm = 0.4;  ///< amplitude of the broken top's roughness
};

/// A straight parting-line flash: a thin wall standing on a body face along a line.
struct StraightFlash {
  std::string region;
  std::array<double, 2> start_mm{0, 0};
  double direction_deg = 0.0;  ///< direction of the line in the part's xy plane
  ValueRange length_mm{50.0, 150.0};
  ValueRange height_mm{1.0, 3.0};
  ValueRange thickness_mm{0.3, 1.5};
  double edge_irregularity_mm = 0.3;
};

/// Per-casting variation and the scene around the part.
struct GeometryVariation {
  double form_deviation_mm = 0.2;        ///< amplitude of the body's smooth form deviation
  double placement_tolerance_mm = 3.0;   ///< placement on the fixture within +- this (x, y)
  double placement_tolerance_deg = 3.0;  ///< and +- this about z
  double placement_tilt_deg = 0.0;       ///< and +- this about x and y (a chip under a locator); 0 = flat
};

struct PartGeometry {
  bool present = false;  ///< the recipe has a [geometry] table
  double surface_grid_mm = 0.1;   ///< body surface (height-field) pitch for rendering and the template
  double material_grid_mm = 0.05;  ///< removable material (dexel) pitch
  GeometryVariation variation;
  int clamps = 2;         ///< fixture clamps beside the part
  int clutter_items = 3;  ///< random objects lying on the table
  std::vector<BodyBlock> blocks;
  std::vector<BodyCylinder> cylinders;
  std::vector<RingFlash> ring_flashes;
  std::vector<Riser> risers;
  std::vector<StraightFlash> straight_flashes;
};

/// The nominal body's top at (x, y), part frame, mm: the highest of the blocks' (tilted) tops and
/// the cylinders' (ring flashes' too) over that point; NaN where no body is. The recipe's checks
/// and the simulator's casting use this one definition.
double nominal_top_z_mm(const PartGeometry& geometry, double x_mm, double y_mm);

}  // namespace fettle::config
