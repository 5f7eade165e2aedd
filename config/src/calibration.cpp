// [calibration] in the cell file, and the calibration file it names (reader and writer).
#include "fettle/config/calibration.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdint>
#include <ctime>
#include <fstream>
#include <iterator>
#include <sstream>
#include <tuple>

#include "fettle/core/atomic_file.hpp"
#include "reader.hpp"
#include "sections.hpp"

namespace fettle::config {

namespace {
using detail::Need;
using detail::Report;
using detail::TableReader;

constexpr double kMaxPx = 100000.0;

void read_transform(TableReader& t, std::optional<Transform>& out) {
  std::array<double, 3> p{};
  std::vector<double> q;
  t.vec3("position_mm", p, detail::kCoordMm, Need::required);
  t.numbers("quaternion_wxyz", q, {-1.0, 1.0}, 4, 4, Need::required);
  if (q.size() != 4) return;
  Quat quat(q[0], q[1], q[2], q[3]);
  const double n = quat.norm();
  if (std::abs(n - 1.0) > 1e-6) {
    t.error("quaternion_wxyz", "is not a unit quaternion (norm " + std::to_string(n) +
                                   "); write w, x, y, z of a rotation with w*w + x*x + y*y + z*z = 1");
    return;
  }
  Pose pose{Vec3(p[0], p[1], p[2]), quat.normalized()};
  out = pose.to_transform();
}

void read_intrinsics(TableReader& t, CameraIntrinsics& k) {
  t.integer("width_px", k.width_px, {1, 100000}, Need::required);
  t.integer("height_px", k.height_px, {1, 100000}, Need::required);
  t.number("fx_px", k.fx_px, {1.0, 1e6}, Need::required);
  t.number("fy_px", k.fy_px, {1.0, 1e6}, Need::required);
  t.number("cx_px", k.cx_px, {0.0, kMaxPx}, Need::required);
  t.number("cy_px", k.cy_px, {0.0, kMaxPx}, Need::required);
  t.number("skew", k.skew, {-1e4, 1e4});
  t.numbers("distortion", k.distortion, {-1e4, 1e4}, 0, 14);
  if (!k.distortion.empty() && k.distortion.size() != 4 && k.distortion.size() != 5 && k.distortion.size() != 8 &&
      k.distortion.size() != 12 && k.distortion.size() != 14)
    t.error("distortion", "must hold 0, 4, 5, 8, 12 or 14 coefficients (OpenCV order k1 k2 p1 p2 k3 ...), got " +
                              std::to_string(k.distortion.size()));
  t.number("rms_px", k.rms_px, {0.0, 1000.0});
  t.integer("views", k.views, {0, 100000});
  if (k.width_px > 0 && k.cx_px > k.width_px) t.error("cx_px", "lies outside the image (width_px is " + std::to_string(k.width_px) + ")");
  if (k.height_px > 0 && k.cy_px > k.height_px)
    t.error("cy_px", "lies outside the image (height_px is " + std::to_string(k.height_px) + ")");
}

void read_hand_eye(TableReader& t, HandEyeResiduals& h) {
  t.choice("method", h.method, {"nominal", "board", "sphere"}, Need::required);
  t.integer("poses", h.poses, {0, 100000});
  t.number("rms_mm", h.rms_mm, {0.0, 1e5});
  t.number("max_mm", h.max_mm, {0.0, 1e5});
  t.number("rms_deg", h.rms_deg, {0.0, 180.0});
  t.number("max_deg", h.max_deg, {0.0, 180.0});
  t.tables("pose", [&](TableReader& p, std::size_t) {
    PoseResidual r;
    p.string("name", r.name, Need::required);
    p.number("translation_mm", r.translation_mm, {0.0, 1e5}, Need::required);
    p.number("rotation_deg", r.rotation_deg, {0.0, 180.0});
    p.boolean("outlier", r.outlier);
    h.per_pose.push_back(r);
  });
}

bool looks_like_iso8601(const std::string& s) {
  // YYYY-MM-DD, optionally followed by a time: enough to sort and read.
  if (s.size() < 10) return false;
  for (std::size_t i = 0; i < 10; ++i) {
    const bool dash = i == 4 || i == 7;
    if (dash ? s[i] != '-' : !std::isdigit(static_cast<unsigned char>(s[i]))) return false;
  }
  return s.size() == 10 || s[10] == 'T' || s[10] == ' ';
}

void read_calibration_file(TableReader& root, CalibrationFile& c) {
  if (auto t = root.table("calibration", Need::required)) {
    t->string("id", c.id, Need::required);
    t->string("date", c.date, Need::required);
    t->string("note", c.note, Need::optional, true);
    if (!c.date.empty() && !looks_like_iso8601(c.date))
      t->error("date", "\"" + c.date + "\" is not an ISO 8601 date such as \"2026-11-22T04:30:00Z\"");
  }
  if (auto t = root.table("intrinsics")) {
    CameraIntrinsics k;
    read_intrinsics(*t, k);
    c.intrinsics = k;
  }
  if (auto t = root.table("T_base_camera")) read_transform(*t, c.T_base_camera);
  if (auto t = root.table("T_flange_board")) read_transform(*t, c.T_flange_board);
  if (auto t = root.table("T_camera_projector")) {
    read_transform(*t, c.T_camera_projector);
    t->number("rms_px", c.stereo_rms_px, {0.0, 1000.0});
  }
  if (auto t = root.table("hand_eye")) {
    HandEyeResiduals h;
    read_hand_eye(*t, h);
    c.hand_eye = h;
  }
  if (c.hand_eye && !c.T_base_camera && !root.has("T_base_camera"))
    root.error("hand_eye", "residuals are given but [T_base_camera] is missing");
}

std::vector<Diagnostic> read(const std::filesystem::path& file, CalibrationFile& c) {
  Report report(file.string());
  auto table = detail::parse_file(file, report);
  if (table) {
    c.source = std::filesystem::absolute(file).lexically_normal();
    std::ifstream in(file, std::ios::binary);
    c.sha256 = sha256_hex(std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()));
    TableReader root(*table, "", report, c.source.parent_path());
    read_calibration_file(root, c);
    root.finish();
  }
  auto d = report.diagnostics();
  std::stable_sort(d.begin(), d.end(), [](const Diagnostic& a, const Diagnostic& b) {
    return std::tie(a.line, a.column) < std::tie(b.line, b.column);
  });
  return d;
}

/// A TOML float (always with a '.' or an exponent so it reads back as a float).
std::string fnum(double v, int digits = 12) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*g", digits, v);
  std::string s(buf);
  if (s.find_first_of(".eEn") == std::string::npos) s += ".0";
  return s;
}

std::string quote(const std::string& s) {
  std::string out = "\"";
  for (const char ch : s) {
    if (ch == '"' || ch == '\\') out += '\\';
    if (ch == '\n') {
      out += "\\n";
      continue;
    }
    out += ch;
  }
  return out + "\"";
}

void write_transform(std::ostringstream& o, const char* name, const Transform& T, const char* comment) {
  const Pose p = Pose::from_transform(T);
  Quat q = p.orientation;
  if (q.w() < 0) q.coeffs() *= -1.0;  // one canonical sign
  const Eigen::AngleAxisd aa(q);
  o << "\n[" << name << "]  # " << comment << "\n";
  o << "position_mm = [" << fnum(p.position_mm.x(), 10) << ", " << fnum(p.position_mm.y(), 10) << ", "
    << fnum(p.position_mm.z(), 10) << "]\n";
  o << "quaternion_wxyz = [" << fnum(q.w(), 15) << ", " << fnum(q.x(), 15) << ", " << fnum(q.y(), 15) << ", "
    << fnum(q.z(), 15) << "]\n";
  o << "# rotation: " << fnum(rad_to_deg(aa.angle()), 6) << " deg about [" << fnum(aa.axis().x(), 6) << ", "
    << fnum(aa.axis().y(), 6) << ", " << fnum(aa.axis().z(), 6) << "]\n";
}

}  // namespace

namespace detail {

void read_calibration(TableReader& root, CalibrationSection& c) {
  auto t = root.table("calibration");
  if (!t) return;
  t->path("file", c.file, Need::optional, /*must_exist=*/true);
  if (c.file.empty() || !std::filesystem::is_regular_file(c.file)) return;
  // A cell file is only valid if the calibration file it names is.
  CalibrationFile cal;
  const auto problems = read(c.file, cal);
  if (!problems.empty()) {
    std::string msg = "calibration file is invalid: " + problems.front().to_string();
    if (problems.size() > 1)
      msg += " (and " + std::to_string(problems.size() - 1) + " more; run `fettle calibrate show " +
             c.file.string() + "`)";
    t->error("file", msg);
  }
}

}  // namespace detail

CalibrationFile load_calibration(const std::filesystem::path& file) {
  CalibrationFile c;
  if (auto d = read(file, c); !d.empty()) throw ConfigError(std::move(d));
  return c;
}

std::vector<CalibrationPose> load_calibration_poses(const std::filesystem::path& file) {
  Report report(file.string());
  std::vector<CalibrationPose> poses;
  if (auto table = detail::parse_file(file, report)) {
    TableReader root(*table, "", report, std::filesystem::absolute(file).parent_path());
    root.tables(
        "pose",
        [&](TableReader& t, std::size_t i) {
          CalibrationPose p;
          p.name = "pose" + std::to_string(i + 1);
          t.string("name", p.name);
          std::array<double, 3> pos{};
          t.vec3("position_mm", pos, detail::kCoordMm, Need::required);
          std::vector<double> q{0.0, 1.0, 0.0, 0.0};
          t.numbers("quaternion_wxyz", q, {-1.0, 1.0}, 4, 4);
          Quat quat(1.0, 0.0, 0.0, 0.0);
          if (q.size() == 4) {
            quat = Quat(q[0], q[1], q[2], q[3]);
            if (std::abs(quat.norm() - 1.0) > 1e-6)
              t.error("quaternion_wxyz", "is not a unit quaternion (norm " + std::to_string(quat.norm()) + ")");
          }
          p.T_base_tool = Pose{Vec3(pos[0], pos[1], pos[2]), quat.normalized()};
          poses.push_back(p);
        },
        Need::required);
    root.finish();
  }
  if (!report.empty()) throw ConfigError(report.diagnostics());
  if (poses.empty()) throw UserError(file.string() + ": no [[pose]] in the file");
  return poses;
}

std::vector<Diagnostic> check_calibration(const std::filesystem::path& file) {
  CalibrationFile c;
  return read(file, c);
}

std::string to_toml(const CalibrationFile& c) {
  std::ostringstream o;
  o << "# Fettle calibration file (format: docs/calibration.md). Lengths in mm, angles in deg,\n"
       "# image coordinates in px. T_target_source maps source-frame points into the target frame.\n\n";
  o << "[calibration]\n";
  o << "id = " << quote(c.id) << "\n";
  o << "date = " << quote(c.date) << "\n";
  if (!c.note.empty()) o << "note = " << quote(c.note) << "\n";
  if (c.intrinsics) {
    const auto& k = *c.intrinsics;
    o << "\n[intrinsics]  # pinhole camera, OpenCV distortion model\n";
    o << "width_px = " << k.width_px << "\n";
    o << "height_px = " << k.height_px << "\n";
    o << "fx_px = " << fnum(k.fx_px) << "\n";
    o << "fy_px = " << fnum(k.fy_px) << "\n";
    o << "cx_px = " << fnum(k.cx_px) << "\n";
    o << "cy_px = " << fnum(k.cy_px) << "\n";
    if (k.skew != 0.0) o << "skew = " << fnum(k.skew) << "\n";
    o << "distortion = [";
    for (std::size_t i = 0; i < k.distortion.size(); ++i) o << (i ? ", " : "") << fnum(k.distortion[i]);
    o << "]  # k1 k2 p1 p2 k3 ...\n";
    o << "rms_px = " << fnum(k.rms_px, 6) << "  # reprojection RMS over the views used\n";
    o << "views = " << k.views << "\n";
  }
  if (c.T_base_camera) write_transform(o, "T_base_camera", *c.T_base_camera, "camera frame -> robot base frame");
  if (c.T_flange_board) write_transform(o, "T_flange_board", *c.T_flange_board, "board frame -> robot flange frame");
  if (c.T_camera_projector) {
    write_transform(o, "T_camera_projector", *c.T_camera_projector, "projector frame -> camera frame");
    o << "rms_px = " << fnum(c.stereo_rms_px, 6) << "  # stereo reprojection RMS\n";
  }
  if (c.hand_eye) {
    const auto& h = *c.hand_eye;
    o << "\n[hand_eye]  # residuals of the hand-eye calibration\n";
    o << "method = " << quote(h.method) << "\n";
    o << "poses = " << h.poses << "\n";
    o << "rms_mm = " << fnum(h.rms_mm, 6) << "\n";
    o << "max_mm = " << fnum(h.max_mm, 6) << "\n";
    o << "rms_deg = " << fnum(h.rms_deg, 6) << "\n";
    o << "max_deg = " << fnum(h.max_deg, 6) << "\n";
    for (const auto& p : h.per_pose) {
      o << "\n[[hand_eye.pose]]\n";
      o << "name = " << quote(p.name) << "\n";
      o << "translation_mm = " << fnum(p.translation_mm, 6) << "\n";
      o << "rotation_deg = " << fnum(p.rotation_deg, 6) << "\n";
      if (p.outlier) o << "outlier = true\n";
    }
  }
  return o.str();
}

void write_calibration(const std::filesystem::path& file, const CalibrationFile& calibration) {
  if (auto s = write_file_atomic(file, to_toml(calibration)); !s.ok())
    throw UserError("cannot write calibration file " + file.string() + ": " + s.error().message);
}

std::string utc_now_iso8601() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

std::string sha256_hex(const std::string& bytes) {
  // FIPS 180-4, straightforward: the calibration file is a few kB.
  static constexpr std::uint32_t k[64] = {
      0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5,
      0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174,
      0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da,
      0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967,
      0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85,
      0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070,
      0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
      0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7, 0xc67178f2};
  std::uint32_t h[8] = {0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a, 0x510e527f, 0x9b05688c, 0x1f83d9ab, 0x5be0cd19};
  std::string m = bytes;
  const std::uint64_t bits = static_cast<std::uint64_t>(bytes.size()) * 8u;
  m += static_cast<char>(0x80);
  while (m.size() % 64 != 56) m += '\0';
  for (int i = 7; i >= 0; --i) m += static_cast<char>((bits >> (8 * i)) & 0xffu);
  const auto rotr = [](std::uint32_t x, int n) { return (x >> n) | (x << (32 - n)); };
  for (std::size_t off = 0; off < m.size(); off += 64) {
    std::uint32_t w[64];
    for (int i = 0; i < 16; ++i)
      w[i] = static_cast<std::uint32_t>(static_cast<unsigned char>(m[off + 4 * i])) << 24 |
             static_cast<std::uint32_t>(static_cast<unsigned char>(m[off + 4 * i + 1])) << 16 |
             static_cast<std::uint32_t>(static_cast<unsigned char>(m[off + 4 * i + 2])) << 8 |
             static_cast<std::uint32_t>(static_cast<unsigned char>(m[off + 4 * i + 3]));
    for (int i = 16; i < 64; ++i) {
      const std::uint32_t s0 = rotr(w[i - 15], 7) ^ rotr(w[i - 15], 18) ^ (w[i - 15] >> 3);
      const std::uint32_t s1 = rotr(w[i - 2], 17) ^ rotr(w[i - 2], 19) ^ (w[i - 2] >> 10);
      w[i] = w[i - 16] + s0 + w[i - 7] + s1;
    }
    std::uint32_t a = h[0], b = h[1], c = h[2], d = h[3], e = h[4], f = h[5], g = h[6], hh = h[7];
    for (int i = 0; i < 64; ++i) {
      const std::uint32_t t1 = hh + (rotr(e, 6) ^ rotr(e, 11) ^ rotr(e, 25)) + ((e & f) ^ (~e & g)) + k[i] + w[i];
      const std::uint32_t t2 = (rotr(a, 2) ^ rotr(a, 13) ^ rotr(a, 22)) + ((a & b) ^ (a & c) ^ (b & c));
      hh = g;
      g = f;
      f = e;
      e = d + t1;
      d = c;
      c = b;
      b = a;
      a = t1 + t2;
    }
    h[0] += a;
    h[1] += b;
    h[2] += c;
    h[3] += d;
    h[4] += e;
    h[5] += f;
    h[6] += g;
    h[7] += hh;
  }
  char out[65];
  for (int i = 0; i < 8; ++i) std::snprintf(out + 8 * i, 9, "%08x", h[i]);
  return std::string(out, 64);
}

Transform T_base_camera_at(const Transform& T_base_camera, double slide_mm) {
  Transform T = T_base_camera;
  T.pretranslate(Vec3(slide_mm, 0.0, 0.0));
  return T;
}

CalibrationIdentity calibration_identity(const CalibrationFile& c) {
  return CalibrationIdentity{c.id, c.date, c.sha256, c.source};
}

std::string CalibrationIdentity::to_string() const {
  std::string s = id + " (" + date + ")";
  if (!sha256.empty()) s += " sha256:" + sha256.substr(0, 12);
  if (!file.empty()) s += " " + file.string();
  return s;
}

}  // namespace fettle::config
