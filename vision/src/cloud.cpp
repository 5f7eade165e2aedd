// Cloud I/O and unit checks.
#include "fettle/vision/cloud.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <optional>
#include <string>

#include <pcl/PCLPointCloud2.h>
#include <pcl/common/io.h>

#include "fettle/core/error.hpp"
#include "fettle/core/ply.hpp"
#include "cloud_readers.hpp"

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

/// Where a field's first value sits in a point, and its PCLPointField datatype.
struct FieldAt {
  std::uint32_t offset = 0;
  std::uint8_t datatype = 0;
};

/// The named field, when the blob has it with a numeric type that fits in a point.
std::optional<FieldAt> field_at(const pcl::PCLPointCloud2& blob, const char* name) {
  const auto it = std::find_if(blob.fields.begin(), blob.fields.end(), [&](const auto& f) { return f.name == name; });
  if (it == blob.fields.end()) return std::nullopt;
  const std::size_t size = pcl::getFieldSize(it->datatype);
  if (size == 0 || it->datatype == pcl::PCLPointField::BOOL || std::size_t{it->offset} + size > blob.point_step)
    return std::nullopt;
  return FieldAt{it->offset, it->datatype};
}

template <typename T>
float read_as(const std::uint8_t* p) {
  T v;
  std::memcpy(&v, p, sizeof v);
  return static_cast<float>(v);
}

/// One value of a PCLPointField datatype as float (field_at() has vetted the type).
float value_at(const std::uint8_t* p, std::uint8_t datatype) {
  using F = pcl::PCLPointField;
  switch (datatype) {
    case F::INT8: return read_as<std::int8_t>(p);
    case F::UINT8: return read_as<std::uint8_t>(p);
    case F::INT16: return read_as<std::int16_t>(p);
    case F::UINT16: return read_as<std::uint16_t>(p);
    case F::INT32: return read_as<std::int32_t>(p);
    case F::UINT32: return read_as<std::uint32_t>(p);
    case F::INT64: return read_as<std::int64_t>(p);
    case F::UINT64: return read_as<std::uint64_t>(p);
    case F::FLOAT64: return read_as<double>(p);
    default: return read_as<float>(p);
  }
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
  if (ext != ".pcd" && ext != ".ply")
    throw UserError(file.string() + ": unknown point-cloud format '" + ext + "' (use .ply or .pcd)");
  // Fettle's own readers: PCL 1.13's PCDReader and PLYReader crash, assert or allocate tens of
  // gigabytes on malformed headers (fuzz_cloud).
  const pcl::PCLPointCloud2 blob = ext == ".pcd" ? detail::read_pcd(file) : detail::read_ply(file);
  const std::size_t total = static_cast<std::size_t>(blob.width) * blob.height;
  if (total == 0) throw UserError(file.string() + ": the point cloud is empty (0 points)");
  // The layout must fit the data read (the readers guarantee it; this keeps the loop below safe
  // on its own).
  for (const auto& f : blob.fields) {
    const std::size_t size = pcl::getFieldSize(f.datatype);
    if (size == 0 || static_cast<std::size_t>(f.offset) + size * std::max<std::size_t>(f.count, 1) > blob.point_step)
      throw UserError(file.string() + ": field '" + f.name + "' does not fit in a point of " +
                      std::to_string(blob.point_step) + " bytes (corrupt header)");
  }
  if (blob.row_step < static_cast<std::size_t>(blob.width) * blob.point_step ||
      blob.data.size() / std::max<std::size_t>(blob.row_step, 1) < blob.height)
    throw UserError(file.string() + ": the header announces " + std::to_string(blob.width) + " x " +
                    std::to_string(blob.height) + " points of " + std::to_string(blob.point_step) + " bytes, the file holds " +
                    std::to_string(blob.data.size()) + " bytes of point data (truncated or corrupt)");
  const auto x = field_at(blob, "x"), y = field_at(blob, "y"), z = field_at(blob, "z");
  if (!x || !y || !z) throw UserError(file.string() + ": the file has no numeric x, y, z fields");
  const auto nx = field_at(blob, "normal_x"), ny = field_at(blob, "normal_y"), nz = field_at(blob, "normal_z");
  const bool normals = nx && ny && nz;

  Cloud out;
  out.points.reserve(total);
  if (normals) out.normals.reserve(total);
  for (std::uint32_t r = 0; r < blob.height; ++r)
    for (std::uint32_t c = 0; c < blob.width; ++c) {
      const std::uint8_t* base =
          blob.data.data() + static_cast<std::size_t>(r) * blob.row_step + static_cast<std::size_t>(c) * blob.point_step;
      const Eigen::Vector3f v(value_at(base + x->offset, x->datatype), value_at(base + y->offset, y->datatype),
                              value_at(base + z->offset, z->datatype));
      if (!v.allFinite()) continue;
      out.points.push_back(v);
      if (!normals) continue;
      const Eigen::Vector3f n(value_at(base + nx->offset, nx->datatype), value_at(base + ny->offset, ny->datatype),
                              value_at(base + nz->offset, nz->datatype));
      out.normals.push_back(n.allFinite() && n.norm() > 0.5f ? Eigen::Vector3f(n.normalized()) : Eigen::Vector3f::Zero());
    }
  // A normal field that is mostly zeros or NaNs is no normal field; a few invalid ones stay
  // zero (no direction: they add nothing to point-to-plane terms).
  const auto invalid = std::count_if(out.normals.begin(), out.normals.end(), [](const auto& n) { return n.isZero(); });
  if (2 * static_cast<std::size_t>(invalid) > out.normals.size()) out.normals.clear();
  if (out.points.empty())
    throw UserError(file.string() + ": the point cloud has " + std::to_string(total) +
                    " points but none is valid (all NaN or infinite)");
  return out;
}

void save_ply(const std::filesystem::path& file, const Cloud& cloud) {
  const bool normals = cloud.has_normals();
  const std::vector<std::string> names = normals ? std::vector<std::string>{"nx", "ny", "nz"} : std::vector<std::string>{};
  const std::span<const float> values =
      normals ? std::span<const float>(cloud.normals.front().data(), 3 * cloud.normals.size()) : std::span<const float>();
  if (auto st = write_ply(file, cloud.points, names, values, "fettle vision cloud, millimetres"); !st)
    throw UserError(st.error().message + " (check the directory exists and is writable)");
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
