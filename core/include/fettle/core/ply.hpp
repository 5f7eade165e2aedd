#pragma once
// PLY files of points, one implementation for every component (the camera's captures, a cycle
// record's clouds, the simulator's views): binary little-endian, float x y z in millimetres.
// An organized cloud keeps its grid in `obj_info num_cols W` / `obj_info num_rows H` header
// lines, as PCL writes and reads them, and its NaN points (no data); a list of points may carry
// one float property per point (a deviation from the template, say). PLY and PCD from other
// writers (ASCII, other layouts) are read by vision::load_cloud.
#include <filesystem>
#include <span>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "fettle/core/cloud.hpp"
#include "fettle/core/result.hpp"

namespace fettle {

/// Writes the organized cloud, NaN points included, atomically; an error ("ply.write") names the file.
Status write_ply(const std::filesystem::path& file, const OrganizedCloud& cloud);
/// Writes the points, each followed by the float properties `extra_names` (a deviation, or nx ny
/// nz) taken in order from `extra`: extra[i * k + j] is point i's property j, k the number of
/// names. `extra` must hold k floats per point. `comment` goes into the header.
Status write_ply(const std::filesystem::path& file, const std::vector<Eigen::Vector3f>& points,
                 const std::vector<std::string>& extra_names = {}, std::span<const float> extra = {},
                 const std::string& comment = "fettle, millimetres");
/// Reads a binary little-endian PLY whose vertices are float x y z followed by any further
/// float properties (skipped): what write_ply writes. A grid that does not match the vertex
/// count becomes one row. Bad input is an error ("ply.bad") naming the file and what is wrong;
/// a header never makes it allocate more than the file holds.
Result<OrganizedCloud> read_ply(const std::filesystem::path& file);

}  // namespace fettle
