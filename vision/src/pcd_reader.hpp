#pragma once
// Fettle's own reader for PCD files (the Point Cloud Library's format, versions .5 to 0.7).
//
// PCL 1.13's PCDReader crashes on many malformed headers (fuzz_cloud found one after another),
// so load_cloud reads PCD itself: every count in the header is checked against the file before
// anything is allocated, and every problem is a UserError that says what is wrong and where.
#include <filesystem>
#include <string>

#include <pcl/PCLPointCloud2.h>

namespace fettle::vision::detail {

/// Reads a PCD file (DATA ascii, binary or binary_compressed) into a PCLPointCloud2 whose point
/// data is packed (row_step = width * point_step, fields in header order). Throws UserError
/// naming the file and the header line or data line at fault.
pcl::PCLPointCloud2 read_pcd(const std::filesystem::path& file);

/// The same for a file already in memory; `name` is used in messages.
pcl::PCLPointCloud2 parse_pcd(const std::string& bytes, const std::string& name);

}  // namespace fettle::vision::detail
