// PLY files of points (ply.hpp).
#include "fettle/core/ply.hpp"

#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>

#include "fettle/core/atomic_file.hpp"

namespace fettle {
namespace {

Status write(const std::filesystem::path& file, const std::string& data) {
  if (auto st = write_file_atomic(file, data); !st)
    return Error{"ply.write", "cannot write " + file.string() + ": " + st.error().message};
  return {};
}

void append_floats(std::string& out, const float* v, std::size_t n) {
  const std::size_t at = out.size();
  out.resize(at + n * sizeof(float));
  std::memcpy(out.data() + at, v, n * sizeof(float));
}

}  // namespace

Status write_ply(const std::filesystem::path& file, const OrganizedCloud& cloud) {
  std::ostringstream header;
  header << "ply\nformat binary_little_endian 1.0\ncomment fettle organized cloud, millimetres, NaN = no data\n"
            "obj_info num_cols "
         << cloud.width << "\nobj_info num_rows " << cloud.height << "\nelement vertex " << cloud.points.size()
         << "\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
  std::string data = header.str();
  data.reserve(data.size() + cloud.points.size() * 12);
  for (const auto& p : cloud.points) append_floats(data, p.data(), 3);  // three contiguous floats
  return write(file, data);
}

Status write_ply(const std::filesystem::path& file, const std::vector<Eigen::Vector3f>& points,
                 const std::vector<std::string>& extra_names, std::span<const float> extra,
                 const std::string& comment) {
  const std::size_t k = extra_names.size();
  if (extra.size() != k * points.size())
    return Error{"ply.write", "cannot write " + file.string() + ": " + std::to_string(extra.size()) +
                                  " property values for " + std::to_string(points.size()) + " points and " +
                                  std::to_string(k) + " properties"};
  std::string data = "ply\nformat binary_little_endian 1.0\ncomment " + comment + "\nelement vertex " +
                     std::to_string(points.size()) + "\nproperty float x\nproperty float y\nproperty float z\n";
  for (const auto& name : extra_names) data += "property float " + name + "\n";
  data += "end_header\n";
  data.reserve(data.size() + points.size() * 4 * (3 + k));
  for (std::size_t i = 0; i < points.size(); ++i) {
    append_floats(data, points[i].data(), 3);
    if (k > 0) append_floats(data, extra.data() + i * k, k);
  }
  return write(file, data);
}

Result<OrganizedCloud> read_ply(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  auto bad = [&](const std::string& why) { return Error{"ply.bad", file.string() + ": " + why}; };
  if (!in) return bad("cannot open");
  std::error_code ec;
  const auto file_size = std::filesystem::file_size(file, ec);
  if (ec) return bad("cannot read its size: " + ec.message());
  std::string line;
  OrganizedCloud cloud;
  std::uint64_t vertices = 0;
  bool binary = false;
  bool end_header = false;
  bool other_property = false;
  std::vector<std::string> floats;  // the float properties' names, in order
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
    std::string w, a, name;
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
      if (a != "vertex") return bad("element '" + a + "': only vertices are read");
      if (!count(words, vertices)) return bad("bad vertex count in '" + line + "' (at most 4294967295)");
    } else if (w == "property") {
      words >> a >> name;
      if (a == "float") floats.push_back(name);
      else other_property = true;
    }
  }
  if (!end_header) return bad("no end_header line");
  if (!binary || other_property || floats.size() < 3 || floats[0] != "x" || floats[1] != "y" || floats[2] != "z")
    return bad("not a binary little-endian PLY with float x y z (and further float properties)");
  const std::uint64_t stride = 4 * floats.size();
  // The header must not promise more vertices than the file holds (nor make us allocate them).
  const auto data_start = static_cast<std::uint64_t>(in.tellg());
  const std::uint64_t available = file_size > data_start ? (file_size - data_start) / stride : 0;
  if (vertices > available)
    return bad("truncated vertex data: the header says " + std::to_string(vertices) + " vertices, the file holds " +
               std::to_string(available));
  if (std::uint64_t{cloud.width} * cloud.height != vertices) {
    cloud.width = static_cast<std::uint32_t>(vertices);
    cloud.height = 1;
  }
  cloud.points.resize(vertices);
  std::vector<char> vertex(stride);
  for (auto& p : cloud.points) {
    if (!in.read(vertex.data(), static_cast<std::streamsize>(stride))) return bad("truncated vertex data");
    float xyz[3];
    std::memcpy(xyz, vertex.data(), sizeof xyz);
    p = Eigen::Vector3f(xyz[0], xyz[1], xyz[2]);
  }
  return cloud;
}

}  // namespace fettle
