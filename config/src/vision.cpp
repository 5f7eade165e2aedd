// [vision] in a part recipe.
#include "fettle/config/vision.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_vision(TableReader& root, VisionSettings& /*v*/) {
  if (auto t = root.table("vision")) {
  }
}

}  // namespace fettle::config::detail
