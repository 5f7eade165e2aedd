#pragma once
// Fettle's own readers for PCD (the Point Cloud Library's format, versions .5 to 0.7) and PLY
// (Stanford polygon files: ascii, binary little and big endian) point clouds.
//
// PCL 1.13's PCDReader and PLYReader crash, assert or allocate tens of gigabytes on malformed
// headers (fuzz_cloud found one after another), so load_cloud reads both formats itself: every
// count in a header is checked against the file before anything is allocated, and every
// problem is a UserError that says what is wrong and where (header line, data line or element).
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

/// Reads the vertex element of a PLY file into a PCLPointCloud2 (width = vertex count, height
/// 1): one field per scalar vertex property in header order, nx/ny/nz named normal_x/y/z as PCL
/// names them; list properties and other elements are skipped. Throws UserError naming the
/// file and the header line or element at fault.
pcl::PCLPointCloud2 read_ply(const std::filesystem::path& file);

/// The same for a file already in memory; `name` is used in messages.
pcl::PCLPointCloud2 parse_ply(const std::string& bytes, const std::string& name);

}  // namespace fettle::vision::detail
