#pragma once
// One reader per section of the cell and part files (private to fettle::config).
// Each device's section lives in its own file: config/src/<section>.cpp.
#include "fettle/config/cell.hpp"
#include "fettle/config/errors.hpp"
#include "fettle/config/part.hpp"
#include "reader.hpp"

namespace fettle::config::detail {

inline constexpr long long kMaxMs = 24LL * 3600 * 1000;
inline constexpr Range<long long> kTimeoutMs{1, kMaxMs};
inline constexpr Range<double> kCoordMm{-1e5, 1e5};

// cell file
void read_plc(TableReader& root, PlcSection& p);
void read_camera(TableReader& root, SlideSection& slide, CameraSection& c);
void read_robot(TableReader& root, RobotSection& r);
void read_spindle(TableReader& root, SpindleSection& s);
void read_calibration(TableReader& root, CalibrationSection& c);

// the simulator's error budget
void read_errors(TableReader& root, ErrorBudget& e);

// part file
void read_geometry(TableReader& root, PartGeometry& g);
void read_vision(TableReader& root, VisionSettings& v);

}  // namespace fettle::config::detail
