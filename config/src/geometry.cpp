// [geometry] in a part recipe.
#include "fettle/config/geometry.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_geometry(TableReader& root, PartGeometry& g) {
  if (auto t = root.table("geometry")) g.present = true;
}

}  // namespace fettle::config::detail
