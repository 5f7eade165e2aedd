// [calibration] in the cell file.
#include "fettle/config/calibration.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_calibration(TableReader& root, CalibrationSection& c) {
  if (auto t = root.table("calibration")) t->path("file", c.file, Need::optional, /*must_exist=*/true);
}

}  // namespace fettle::config::detail
