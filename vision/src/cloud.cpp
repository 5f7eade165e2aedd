// Cloud I/O and unit checks.
#include "fettle/vision/cloud.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>
#include <string>

#include <pcl/PCLPointCloud2.h>
#include <pcl/conversions.h>
#include <pcl/io/pcd_io.h>
#include <pcl/io/ply_io.h>
#include <pcl/point_types.h>

#include "fettle/core/error.hpp"

namespace fettle::vision {

Bounds bounds(const Cloud& cloud) {
  Bounds b;
  if (cloud.empty()) return b;
  b.min = b.max = cloud.points.front();
  for (const auto& p : cloud.points) {
    b.min = b.min.cwiseMin(p);
    b.max = b.max.cwiseMax(p);
  }
  return b;
}

namespace {

bool has_field(const pcl::PCLPointCloud2& blob, const std::string& name) {
  return std::any_of(blob.fields.begin(), blob.fields.end(), [&](const auto& f) { return f.name == name; });
}

std::string lower_extension(const std::filesystem::path& file) {
  std::string ext = file.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext;
}

}  // namespace

Cloud load_cloud(const std::filesystem::path& file) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec))
    throw UserError(file.string() + ": no such file (expected a PLY or PCD point cloud)");
  const std::string ext = lower_extension(file);
  pcl::PCLPointCloud2 blob;
  int rc = -1;
  if (ext == ".pcd") {
    pcl::PCDReader reader;
    rc = reader.read(file.string(), blob);
  } else if (ext == ".ply") {
    pcl::PLYReader reader;
    rc = reader.read(file.string(), blob);
  } else {
    throw UserError(file.string() + ": unknown point-cloud format '" + ext + "' (use .ply or .pcd)");
  }
  if (rc < 0) throw UserError(file.string() + ": cannot read the point cloud (corrupt or not a PLY/PCD file)");
  if (!has_field(blob, "x") || !has_field(blob, "y") || !has_field(blob, "z"))
    throw UserError(file.string() + ": the file has no x, y, z fields");
  const std::size_t total = static_cast<std::size_t>(blob.width) * blob.height;
  if (total == 0) throw UserError(file.string() + ": the point cloud is empty (0 points)");

  Cloud out;
  const bool normals = has_field(blob, "normal_x") && has_field(blob, "normal_y") && has_field(blob, "normal_z");
  if (normals) {
    pcl::PointCloud<pcl::PointNormal> pc;
    pcl::fromPCLPointCloud2(blob, pc);
    out.points.reserve(pc.size());
    out.normals.reserve(pc.size());
    for (const auto& p : pc) {
      const Eigen::Vector3f v = p.getVector3fMap();
      const Eigen::Vector3f n = p.getNormalVector3fMap();
      if (!v.allFinite()) continue;
      out.points.push_back(v);
      out.normals.push_back(n.allFinite() && n.norm() > 0.5f ? Eigen::Vector3f(n.normalized()) : Eigen::Vector3f::Zero());
    }
    // A normal field that is mostly zeros or NaNs is no normal field; a few invalid ones
    // stay zero (no direction: they add nothing to point-to-plane terms).
    const auto invalid = std::count_if(out.normals.begin(), out.normals.end(), [](const auto& n) { return n.isZero(); });
    if (2 * static_cast<std::size_t>(invalid) > out.normals.size()) out.normals.clear();
  } else {
    pcl::PointCloud<pcl::PointXYZ> pc;
    pcl::fromPCLPointCloud2(blob, pc);
    out.points.reserve(pc.size());
    for (const auto& p : pc) {
      const Eigen::Vector3f v = p.getVector3fMap();
      if (v.allFinite()) out.points.push_back(v);
    }
  }
  if (out.points.empty())
    throw UserError(file.string() + ": the point cloud has " + std::to_string(total) +
                    " points but none is valid (all NaN or infinite)");
  return out;
}

void save_ply(const std::filesystem::path& file, const Cloud& cloud) {
  const bool normals = cloud.has_normals();
  std::ofstream out(file, std::ios::binary);
  if (!out) throw UserError(file.string() + ": cannot write (check the directory exists and is writable)");
  out << "ply\nformat binary_little_endian 1.0\nelement vertex " << cloud.size()
      << "\nproperty float x\nproperty float y\nproperty float z\n";
  if (normals) out << "property float nx\nproperty float ny\nproperty float nz\n";
  out << "end_header\n";
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    out.write(reinterpret_cast<const char*>(cloud.points[i].data()), 3 * sizeof(float));
    if (normals) out.write(reinterpret_cast<const char*>(cloud.normals[i].data()), 3 * sizeof(float));
  }
  if (!out) throw UserError(file.string() + ": write failed (disk full?)");
}

Cloud to_cloud(const OrganizedCloud& organized) {
  Cloud out;
  out.points.reserve(organized.size());
  for (const auto& p : organized.points)
    if (p.allFinite()) out.points.push_back(p);
  return out;
}

Cloud transformed(const Cloud& cloud, const Transform& T_target_source) {
  const Eigen::Matrix3f R = T_target_source.rotation().cast<float>();
  const Eigen::Vector3f t = T_target_source.translation().cast<float>();
  Cloud out;
  out.points.resize(cloud.size());
  for (std::size_t i = 0; i < cloud.size(); ++i) out.points[i] = R * cloud.points[i] + t;
  if (cloud.has_normals()) {
    out.normals.resize(cloud.size());
    for (std::size_t i = 0; i < cloud.size(); ++i) out.normals[i] = R * cloud.normals[i];
  }
  return out;
}

void require_millimetres(const Cloud& cloud, const std::string& what) {
  if (cloud.empty()) throw UserError(what + ": the point cloud is empty");
  const double extent = bounds(cloud).diagonal();
  if (extent < 5.0) {
    std::ostringstream s;
    s << what << ": the cloud spans only " << extent
      << " units; Fettle expects millimetres and this looks like metres. Scale it by 1000 "
         "(or export the scan in mm).";
    throw UserError(s.str());
  }
  if (extent > 1e5) {
    std::ostringstream s;
    s << what << ": the cloud spans " << extent << " units (over 100 m if millimetres); check its unit and crop it";
    throw UserError(s.str());
  }
}

}  // namespace fettle::vision
