// Trajectory files (trajectory_io.hpp).
#include "fettle/core/trajectory_io.hpp"

#include <algorithm>
#include <fstream>
#include <iomanip>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "fettle/core/atomic_file.hpp"
#include "fettle/core/error.hpp"

namespace fettle {
namespace {

MoveKind move_kind_from(const std::string& s, const std::string& where) {
  if (s == "approach") return MoveKind::approach;
  if (s == "grind") return MoveKind::grind;
  if (s == "air") return MoveKind::air;
  if (s == "retract") return MoveKind::retract;
  throw UserError(where + ": kind \"" + s + "\" is not one of approach, grind, air, retract");
}

double parse_number(const std::string& s, const std::string& where) {
  try {
    std::size_t used = 0;
    const double v = std::stod(s, &used);
    if (s.find_first_not_of(" \t\r", used) != std::string::npos) throw std::invalid_argument(s);
    return v;
  } catch (const std::exception&) {
    throw UserError(where + ": \"" + s + "\" is not a number");
  }
}

Trajectory read_json(const std::filesystem::path& path, const std::string& text) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text, nullptr, true, false);
  } catch (const nlohmann::json::parse_error& e) {
    const std::size_t off = std::min<std::size_t>(e.byte, text.size());
    const auto line = 1 + std::count(text.begin(), text.begin() + static_cast<std::ptrdiff_t>(off), '\n');
    throw UserError(path.string() + ":" + std::to_string(line) + ": JSON syntax error: " + e.what());
  }
  Trajectory t;
  try {
    t.part_id = j.value("part_id", "");
    if (j.contains("segment_regions")) t.segment_regions = j.at("segment_regions").get<std::vector<std::string>>();
    std::size_t i = 0;
    for (const auto& p : j.at("points")) {
      const std::string where = path.string() + ": points[" + std::to_string(i) + "]";
      TrajectoryPoint q;
      auto get = [&](const char* k) {
        const auto& v = p.at(k);
        if (v.is_string()) return parse_number(v.get<std::string>(), where + "." + k);
        return v.get<double>();
      };
      q.T_base_tool.position_mm = Vec3(get("x"), get("y"), get("z"));
      q.T_base_tool.orientation = Quat(get("qw"), get("qx"), get("qy"), get("qz"));
      q.speed_mm_s = get("speed_mm_s");
      q.spindle_rpm = get("spindle_rpm");
      q.segment = p.value("segment", 0);
      if (p.contains("kind")) q.kind = move_kind_from(p.at("kind").get<std::string>(), where);
      t.points.push_back(q);
      ++i;
    }
  } catch (const nlohmann::json::exception& e) {
    throw UserError(path.string() + ": point " + std::to_string(t.points.size()) + ": " + e.what() +
                    " (each point needs x, y, z, qw, qx, qy, qz, speed_mm_s, spindle_rpm)");
  }
  return t;
}

Trajectory read_csv(const std::filesystem::path& path, const std::string& text) {
  Trajectory t;
  std::istringstream lines(text);
  std::string line;
  int lineno = 0;
  std::vector<std::string> header;
  while (std::getline(lines, line)) {
    ++lineno;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty() || line[0] == '#') continue;
    std::vector<std::string> cells;
    std::stringstream ls(line);
    std::string cell;
    while (std::getline(ls, cell, ',')) cells.push_back(cell);
    const std::string where = path.string() + ":" + std::to_string(lineno);
    if (header.empty()) {
      header = cells;
      const std::vector<std::string> need{"x",  "y",  "z",          "qw",          "qx",
                                          "qy", "qz", "speed_mm_s", "spindle_rpm", "segment"};
      for (std::size_t k = 0; k < need.size(); ++k)
        if (k >= header.size() || header[k] != need[k])
          throw UserError(where + ": the header must be x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment[,kind]");
      continue;
    }
    if (cells.size() < 10)
      throw UserError(where + ": expected at least 10 values, got " + std::to_string(cells.size()));
    double v[9];
    for (std::size_t k = 0; k < 9; ++k) v[k] = parse_number(cells[k], where + ": column " + header[k]);
    TrajectoryPoint q;
    q.T_base_tool.position_mm = Vec3(v[0], v[1], v[2]);
    q.T_base_tool.orientation = Quat(v[3], v[4], v[5], v[6]);
    q.speed_mm_s = v[7];
    q.spindle_rpm = v[8];
    q.segment = static_cast<int>(parse_number(cells[9], where + ": column segment"));
    if (cells.size() > 10) q.kind = move_kind_from(cells[10], where);
    t.points.push_back(q);
  }
  if (header.empty()) throw UserError(path.string() + ": empty trajectory file");
  return t;
}

}  // namespace

const char* move_kind_name(MoveKind kind) {
  switch (kind) {
    case MoveKind::approach:
      return "approach";
    case MoveKind::grind:
      return "grind";
    case MoveKind::air:
      return "air";
    case MoveKind::retract:
      return "retract";
  }
  return "grind";
}

Status write_trajectory_json(const std::filesystem::path& path, const Trajectory& trajectory) {
  nlohmann::ordered_json j;
  j["part_id"] = trajectory.part_id;
  j["segment_regions"] = trajectory.segment_regions;
  auto pts = nlohmann::ordered_json::array();
  for (const auto& p : trajectory.points) {
    const auto& x = p.T_base_tool.position_mm;
    const auto& q = p.T_base_tool.orientation;
    pts.push_back(nlohmann::ordered_json{{"x", x.x()},
                                         {"y", x.y()},
                                         {"z", x.z()},
                                         {"qw", q.w()},
                                         {"qx", q.x()},
                                         {"qy", q.y()},
                                         {"qz", q.z()},
                                         {"speed_mm_s", p.speed_mm_s},
                                         {"spindle_rpm", p.spindle_rpm},
                                         {"segment", p.segment},
                                         {"kind", move_kind_name(p.kind)}});
  }
  j["points"] = std::move(pts);
  return write_file_atomic(path, j.dump(1) + "\n");
}

Status write_trajectory_csv(const std::filesystem::path& path, const Trajectory& trajectory) {
  std::ostringstream os;
  os << "x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment,kind\n";
  os << std::setprecision(std::numeric_limits<double>::max_digits10);
  for (const auto& p : trajectory.points) {
    const auto& x = p.T_base_tool.position_mm;
    const auto& q = p.T_base_tool.orientation;
    os << x.x() << ',' << x.y() << ',' << x.z() << ',' << q.w() << ',' << q.x() << ',' << q.y() << ',' << q.z() << ','
       << p.speed_mm_s << ',' << p.spindle_rpm << ',' << p.segment << ',' << move_kind_name(p.kind) << '\n';
  }
  return write_file_atomic(path, os.str());
}

Trajectory read_trajectory(const std::filesystem::path& path) {
  std::ifstream in(path);
  if (!in) throw UserError(path.string() + ": cannot open the trajectory file");
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string text = ss.str();
  const auto first = text.find_first_not_of(" \t\r\n");
  if (first != std::string::npos && text[first] == '{') return read_json(path, text);
  return read_csv(path, text);
}

}  // namespace fettle
