// Organized clouds to and from PLY (see camera_ply.hpp).
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>

#include "fettle/core/atomic_file.hpp"
#include "fettle/drivers/camera_ply.hpp"

namespace fettle::drivers {

Status write_ply(const std::filesystem::path& file, const OrganizedCloud& cloud) {
  std::ostringstream header;
  header << "ply\nformat binary_little_endian 1.0\ncomment fettle organized cloud, millimetres, camera frame, "
            "NaN = no data\nobj_info num_cols "
         << cloud.width << "\nobj_info num_rows " << cloud.height << "\nelement vertex " << cloud.points.size()
         << "\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
  std::string data = header.str();
  const std::size_t head = data.size();
  data.resize(head + cloud.points.size() * 12);
  char* out = data.data() + head;
  for (const auto& p : cloud.points) {
    std::memcpy(out, p.data(), 12);  // Eigen::Vector3f is three contiguous floats
    out += 12;
  }
  auto status = write_file_atomic(file, data);
  if (!status) return Error{"camera.write_failed", "cannot write " + file.string() + ": " + status.error().message};
  return {};
}

Result<OrganizedCloud> read_ply(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  auto bad = [&](const std::string& why) { return Error{"camera.bad_ply", file.string() + ": " + why}; };
  if (!in) return bad("cannot open");
  std::error_code ec;
  const auto file_size = std::filesystem::file_size(file, ec);
  if (ec) return bad("cannot read its size: " + ec.message());
  std::string line;
  OrganizedCloud cloud;
  std::uint64_t vertices = 0;
  bool binary = false;
  bool end_header = false;
  int float_props = 0;
  // A number of vertices or a grid size: decimal digits only (no sign), at most 2^32 - 1.
  auto count = [](std::istringstream& words, std::uint64_t& out) {
    std::string digits;
    words >> digits;
    if (digits.empty() || digits.size() > 10 || digits.find_first_not_of("0123456789") != std::string::npos)
      return false;
    out = std::stoull(digits);
    return out <= std::numeric_limits<std::uint32_t>::max();
  };
  while (std::getline(in, line)) {
    if (line == "end_header") {
      end_header = true;
      break;
    }
    std::istringstream words(line);
    std::string w, a;
    words >> w;
    if (w == "format") {
      words >> a;
      binary = a == "binary_little_endian";
    } else if (w == "obj_info") {
      words >> a;
      std::uint64_t n = 0;
      if ((a == "num_cols" || a == "num_rows") && !count(words, n)) return bad("bad " + a + " in '" + line + "'");
      if (a == "num_cols") cloud.width = static_cast<std::uint32_t>(n);
      if (a == "num_rows") cloud.height = static_cast<std::uint32_t>(n);
    } else if (w == "element") {
      words >> a;
      if (!count(words, vertices)) return bad("bad vertex count in '" + line + "' (at most 4294967295)");
    } else if (w == "property") {
      words >> a;
      float_props += a == "float" ? 1 : 100;
    }
  }
  if (!end_header) return bad("no end_header line");
  if (!binary || float_props != 3) return bad("not a binary little-endian PLY with float x y z");
  // The header must not promise more vertices than the file holds (nor make us allocate them).
  const auto data_start = static_cast<std::uint64_t>(in.tellg());
  const std::uint64_t available = file_size > data_start ? (file_size - data_start) / 12 : 0;
  if (vertices > available)
    return bad("truncated vertex data: the header says " + std::to_string(vertices) + " vertices, the file holds " +
               std::to_string(available));
  if (std::uint64_t{cloud.width} * cloud.height != vertices) {
    cloud.width = static_cast<std::uint32_t>(vertices);
    cloud.height = 1;
  }
  cloud.points.resize(vertices);
  for (auto& p : cloud.points) {
    float xyz[3];
    if (!in.read(reinterpret_cast<char*>(xyz), sizeof xyz)) return bad("truncated vertex data");
    p = Eigen::Vector3f(xyz[0], xyz[1], xyz[2]);
  }
  return cloud;
}

}  // namespace fettle::drivers
