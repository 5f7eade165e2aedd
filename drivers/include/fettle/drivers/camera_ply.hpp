#pragma once
// Organized clouds to and from PLY files (binary little-endian, float x y z, NaN = no data).
// The grid size is kept in `obj_info num_cols W` / `obj_info num_rows H` header lines, as PCL
// writes and reads them for organized clouds.
#include <filesystem>

#include "fettle/core/cloud.hpp"
#include "fettle/core/result.hpp"

namespace fettle::drivers {

/// Writes the cloud atomically; an error names the file.
Status write_ply(const std::filesystem::path& file, const OrganizedCloud& cloud);
/// Reads a file written by write_ply (binary little-endian vertex x y z floats).
Result<OrganizedCloud> read_ply(const std::filesystem::path& file);

}  // namespace fettle::drivers
