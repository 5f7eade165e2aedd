#pragma once
// The part's parametric geometry ([geometry] in a part recipe), used by the simulator
// to build the casting and its golden template.
namespace fettle::config {

struct PartGeometry {
  bool present = false;  ///< the recipe has a [geometry] table
};

}  // namespace fettle::config
