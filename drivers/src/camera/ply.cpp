// Organized clouds to and from PLY (see camera_ply.hpp).
#include <cstring>
#include <fstream>
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
  std::string line;
  OrganizedCloud cloud;
  std::size_t vertices = 0;
  bool binary = false;
  int float_props = 0;
  while (std::getline(in, line)) {
    if (line == "end_header") break;
    std::istringstream words(line);
    std::string w, a;
    words >> w;
    if (w == "format") {
      words >> a;
      binary = a == "binary_little_endian";
    } else if (w == "obj_info") {
      words >> a;
      if (a == "num_cols") words >> cloud.width;
      if (a == "num_rows") words >> cloud.height;
    } else if (w == "element") {
      words >> a >> vertices;
    } else if (w == "property") {
      words >> a;
      float_props += a == "float" ? 1 : 100;
    }
  }
  if (!binary || float_props != 3) return bad("not a binary little-endian PLY with float x y z");
  if (std::size_t{cloud.width} * cloud.height != vertices) {
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
