// Cloud I/O and unit checks.
#include "fettle/vision/cloud.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>

#include <pcl/PCLPointCloud2.h>
#include <pcl/common/io.h>
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

/// Byte offsets of the named fields when each is one FLOAT32 (the PLY and PCD files Fettle and
/// most scanners write), else nothing.
template <std::size_t N>
std::optional<std::array<std::uint32_t, N>> float32_offsets(const pcl::PCLPointCloud2& blob,
                                                            const std::array<const char*, N>& names) {
  std::array<std::uint32_t, N> out{};
  for (std::size_t k = 0; k < N; ++k) {
    const auto it = std::find_if(blob.fields.begin(), blob.fields.end(), [&](const auto& f) { return f.name == names[k]; });
    if (it == blob.fields.end() || it->datatype != pcl::PCLPointField::FLOAT32 || it->count != 1 ||
        it->offset + sizeof(float) > blob.point_step)
      return std::nullopt;
    out[k] = it->offset;
  }
  return out;
}

std::string lower_extension(const std::filesystem::path& file) {
  std::string ext = file.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext;
}

// Fewest bytes one value of a PLY/PCD type takes in the file: binary, its size; ASCII, a digit
// and a separator.
std::uint64_t min_value_bytes(bool ascii, std::uint64_t binary_size) { return ascii ? 2 : binary_size; }

std::uint64_t ply_type_size(const std::string& t) {
  if (t == "char" || t == "uchar" || t == "int8" || t == "uint8") return 1;
  if (t == "short" || t == "ushort" || t == "int16" || t == "uint16") return 2;
  if (t == "double" || t == "float64") return 8;
  return 4;  // int, uint, float and their sized names
}

// Checks that the element / point counts a PLY or PCD header claims fit in the file, before
// PCL allocates memory for them (a header claiming billions of points would otherwise make it
// allocate gigabytes), and that there is a header at all. Returns the problem, or an empty
// string. Counts that cannot be read are left to PCL's own parser.
std::string implausible_header(const std::filesystem::path& file, bool pcd) {
  std::ifstream in(file, std::ios::binary);
  std::error_code ec;
  const std::uint64_t size = std::filesystem::file_size(file, ec);
  if (!in || ec) return {};
  std::string line;
  std::uint64_t needed = 0;  // bytes the claimed data needs at least
  std::string claimed;       // what the header claims, for the message
  bool ascii = false;
  bool compressed = false;
  bool header_complete = false;
  if (pcd) {
    std::vector<std::uint64_t> sizes, counts;
    std::vector<std::string> fields, types;
    std::uint64_t width = 0, height = 1, points = 0;
    auto read_u64 = [](std::istringstream& w, std::uint64_t& out) {
      std::string t;
      w >> t;
      if (t.empty() || t.size() > 19 || t.find_first_not_of("0123456789") != std::string::npos) return;
      out = std::stoull(t);
    };
    static const std::vector<std::string> keys = {"VERSION", "FIELDS", "SIZE",   "TYPE", "COUNT",
                                                   "WIDTH",   "HEIGHT", "VIEWPOINT", "POINTS", "DATA"};
    while (std::getline(in, line)) {
      if (!line.empty() && line.back() == '\r') line.pop_back();
      // Only printable header lines with known keys (PCL 1.13 crashes on some others).
      if (!std::all_of(line.begin(), line.end(), [](char c) { return c >= 0x20 && c < 0x7F; }))
        return "the PCD header has a line with binary bytes: not a PCD file, or corrupt";
      std::istringstream w(line);
      std::string key;
      w >> key;
      if (key.empty() || key[0] == '#') continue;
      if (std::find(keys.begin(), keys.end(), key) == keys.end())
        return "the PCD header has an unknown line '" + line.substr(0, 40) + "': not a PCD file, or corrupt";
      if (key == "FIELDS" || key == "TYPE") {
        auto& v = key == "FIELDS" ? fields : types;
        for (std::string x; w >> x;) v.push_back(x);
      } else if (key == "SIZE" || key == "COUNT") {
        auto& v = key == "SIZE" ? sizes : counts;
        for (std::uint64_t x = 0; w >> x;) v.push_back(std::min<std::uint64_t>(x, 1U << 20));
      } else if (key == "WIDTH") {
        read_u64(w, width);
      } else if (key == "HEIGHT") {
        read_u64(w, height);
      } else if (key == "POINTS") {
        read_u64(w, points);
      } else if (key == "DATA") {
        std::string format;
        w >> format;
        ascii = format == "ascii";
        compressed = format == "binary_compressed";
        header_complete = true;
        break;
      }
    }
    // PCL 1.13 crashes on a header whose FIELDS, SIZE, TYPE and COUNT do not agree.
    const bool sizes_ok = std::all_of(sizes.begin(), sizes.end(), [](auto x) { return x == 1 || x == 2 || x == 4 || x == 8; });
    const bool types_ok =
        std::all_of(types.begin(), types.end(), [](const std::string& t) { return t == "I" || t == "U" || t == "F"; });
    // COUNT 0: PCL drops the field and then crashes reading the data (fuzz_cloud).
    const bool counts_ok = std::all_of(counts.begin(), counts.end(), [](auto x) { return x > 0; });
    if (header_complete && (fields.empty() || sizes.size() != fields.size() || types.size() != fields.size() ||
                            (!counts.empty() && counts.size() != fields.size()) || !sizes_ok || !types_ok || !counts_ok))
      return "the PCD header's FIELDS, SIZE, TYPE and COUNT lines do not describe the same fields "
             "(SIZE 1, 2, 4 or 8; TYPE I, U or F; COUNT 1 or more)";
    std::uint64_t step = 0;
    for (std::size_t i = 0; i < sizes.size(); ++i)
      step += min_value_bytes(ascii, sizes[i]) * (i < counts.size() ? counts[i] : 1);
    width = std::min<std::uint64_t>(width, 1ULL << 32);
    height = std::min<std::uint64_t>(height, 1ULL << 32);
    const std::uint64_t n = std::max(points, width * height);
    needed = n > 0 && step > (1ULL << 62) / n ? (1ULL << 62) : n * step;
    claimed = std::to_string(n) + " points";
  } else {
    std::uint64_t count = 0, element_bytes = 0;
    auto close_element = [&] {
      const std::uint64_t add = count > 0 && element_bytes > (1ULL << 62) / count ? (1ULL << 62) : count * element_bytes;
      needed = std::min<std::uint64_t>(needed + add, 1ULL << 62);
      count = element_bytes = 0;
    };
    if (!std::getline(in, line) || line.rfind("ply", 0) != 0) return "not a PLY file (it does not start with 'ply')";
    while (std::getline(in, line)) {
      if (!line.empty() && line.back() == '\r') line.pop_back();
      std::istringstream w(line);
      std::string key;
      w >> key;
      if (key == "format") {
        std::string format;
        w >> format;
        ascii = format == "ascii";
      } else if (key == "element") {
        close_element();
        std::string name, t;
        w >> name >> t;
        if (!t.empty() && t.size() <= 19 && t.find_first_not_of("0123456789") == std::string::npos) count = std::stoull(t);
        if (name == "vertex") claimed = t + " vertices";
      } else if (key == "property") {
        std::string type;
        w >> type;
        if (type == "list") w >> type;  // a list has at least its count
        element_bytes += min_value_bytes(ascii, ply_type_size(type));
      } else if (key == "end_header") {
        header_complete = true;
        break;
      }
    }
    close_element();
  }
  // (PCL 1.13's PCDReader crashes on a file without a header, e.g. an empty one.)
  if (!header_complete || !in)
    return pcd ? "no PCD header (no DATA line): not a PCD file, or truncated"
               : "no PLY header (no end_header line): not a PLY file, or truncated";
  const auto header_end = static_cast<std::uint64_t>(in.tellg());
  const std::uint64_t data = size > header_end ? size - header_end : 0;
  // LZF (binary_compressed PCD) shrinks data at most about 100 times.
  const std::uint64_t capacity = compressed ? data * 100 : data;
  if (needed <= capacity) return {};
  return "the header claims " + claimed + " (at least " + std::to_string(needed) + " bytes" +
         (compressed ? " uncompressed" : "") + ") but the file holds " + std::to_string(data) +
         " bytes of data: truncated or corrupt";
}

}  // namespace

Cloud load_cloud(const std::filesystem::path& file) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec))
    throw UserError(file.string() + ": no such file (expected a PLY or PCD point cloud)");
  const std::string ext = lower_extension(file);
  if (ext == ".pcd" || ext == ".ply") {
    if (const auto why = implausible_header(file, ext == ".pcd"); !why.empty()) throw UserError(file.string() + ": " + why);
  }
  pcl::PCLPointCloud2 blob;
  int rc = -1;
  if (ext != ".pcd" && ext != ".ply")
    throw UserError(file.string() + ": unknown point-cloud format '" + ext + "' (use .ply or .pcd)");
  try {
    if (ext == ".pcd") {
      pcl::PCDReader reader;
      rc = reader.read(file.string(), blob);
    } else {
      pcl::PLYReader reader;
      rc = reader.read(file.string(), blob);
    }
  } catch (const std::exception& e) {
    // PCL 1.13's readers throw on some headers, e.g. std::out_of_range for a DATA line
    // without its value (found by fuzz_cloud).
    throw UserError(file.string() + ": cannot read the point cloud, corrupt header (" + e.what() + ")");
  }
  if (rc < 0) throw UserError(file.string() + ": cannot read the point cloud (corrupt or not a PLY/PCD file)");
  if (!has_field(blob, "x") || !has_field(blob, "y") || !has_field(blob, "z"))
    throw UserError(file.string() + ": the file has no x, y, z fields");
  const std::size_t total = static_cast<std::size_t>(blob.width) * blob.height;
  if (total == 0) throw UserError(file.string() + ": the point cloud is empty (0 points)");
  // The layout the header announces must fit the data read; PCL's conversions trust it (a
  // binary PCD whose header lies made fromPCLPointCloud2 read past the buffer; fuzz_cloud).
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

  Cloud out;
  const bool normals = has_field(blob, "normal_x") && has_field(blob, "normal_y") && has_field(blob, "normal_z");
  if (normals) {
    auto keep = [&](const Eigen::Vector3f& v, const Eigen::Vector3f& n) {
      if (!v.allFinite()) return;
      out.points.push_back(v);
      out.normals.push_back(n.allFinite() && n.norm() > 0.5f ? Eigen::Vector3f(n.normalized()) : Eigen::Vector3f::Zero());
    };
    out.points.reserve(total);
    out.normals.reserve(total);
    // Read float fields in place; PCL's PointNormal conversion wants a curvature field as well
    // and prints "Failed to find match for field 'curvature'" for every file without one.
    const auto at = float32_offsets(blob, std::array{"x", "y", "z", "normal_x", "normal_y", "normal_z"});
    if (at) {  // the layout fits the data (checked above)
      for (std::uint32_t r = 0; r < blob.height; ++r)
        for (std::uint32_t c = 0; c < blob.width; ++c) {
          const std::uint8_t* base = blob.data.data() + static_cast<std::size_t>(r) * blob.row_step +
                                     static_cast<std::size_t>(c) * blob.point_step;
          float f[6];
          for (std::size_t k = 0; k < 6; ++k) std::memcpy(&f[k], base + (*at)[k], sizeof(float));
          keep(Eigen::Vector3f(f[0], f[1], f[2]), Eigen::Vector3f(f[3], f[4], f[5]));
        }
    } else {
      pcl::PointCloud<pcl::PointNormal> pc;
      pcl::fromPCLPointCloud2(blob, pc);
      for (const auto& p : pc) keep(p.getVector3fMap(), p.getNormalVector3fMap());
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
