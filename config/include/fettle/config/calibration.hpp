#pragma once
// Calibration: [calibration] in the cell file names the calibration file (issue: calibration).
#include <filesystem>

namespace fettle::config {

struct CalibrationSection {
  std::filesystem::path file;  ///< calibration file (T_base_camera, intrinsics); empty = none yet
};

}  // namespace fettle::config
