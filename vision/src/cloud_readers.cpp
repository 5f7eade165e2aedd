// Fettle's own PCD and PLY readers (see cloud_readers.hpp for why).
#include "cloud_readers.hpp"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <limits>
#include <optional>
#include <string_view>
#include <vector>

#include <pcl/common/io.h>
#include <pcl/io/lzf.h>

#include "fettle/core/error.hpp"

namespace fettle::vision::detail {

namespace {

constexpr std::size_t kMaxHeaderBytes = 1 << 20;  // a real header is a few hundred bytes
constexpr std::size_t kMaxHeaderLine = 1 << 16;
constexpr std::uint64_t kMaxCount = 1 << 16;      // values per field (FPFH has 33, VFH 308)
// LZF (binary_compressed) expands at most 88 times (a 3-byte back reference yields 264 bytes).
constexpr std::uint64_t kMaxLzfRatio = 100;

/// The words of a line; at most `limit` of them (the rest is not looked at).
std::vector<std::string_view> split(std::string_view line, std::size_t limit = std::numeric_limits<std::size_t>::max()) {
  std::vector<std::string_view> out;
  std::size_t i = 0;
  while (i < line.size() && out.size() < limit) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t')) ++i;
    const std::size_t start = i;
    while (i < line.size() && line[i] != ' ' && line[i] != '\t') ++i;
    if (i > start) out.push_back(line.substr(start, i - start));
  }
  return out;
}

/// Printable rendering of a (possibly binary) header line for a message.
std::string shown(std::string_view s) {
  std::string out;
  for (const char c : s.substr(0, 40)) out += c >= 0x20 && c < 0x7F ? c : '?';
  if (s.size() > 40) out += "...";
  return out;
}

std::optional<std::uint64_t> parse_uint(std::string_view t) {
  std::uint64_t v = 0;
  const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), v);
  if (ec != std::errc() || end != t.data() + t.size()) return std::nullopt;
  return v;
}

std::uint8_t datatype_of(char type, std::uint64_t size) {
  using F = pcl::PCLPointField;
  if (type == 'I') return size == 1 ? F::INT8 : size == 2 ? F::INT16 : size == 4 ? F::INT32 : size == 8 ? F::INT64 : 0;
  if (type == 'U') return size == 1 ? F::UINT8 : size == 2 ? F::UINT16 : size == 4 ? F::UINT32 : size == 8 ? F::UINT64 : 0;
  if (type == 'F') return size == 4 ? F::FLOAT32 : size == 8 ? F::FLOAT64 : 0;
  if (type == 'B') return size == 1 ? F::UINT8 : 0;  // bool, as PCL writes it: read as 0 / 1
  return 0;
}

template <typename T>
bool store_int(std::string_view t, std::uint8_t* out) {
  if (!t.empty() && t.front() == '+') t.remove_prefix(1);
  T v{};
  const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), v);
  if (ec != std::errc() || end != t.data() + t.size()) return false;
  std::memcpy(out, &v, sizeof v);
  return true;
}

template <typename T>
bool store_float(std::string_view t, std::uint8_t* out) {
  if (!t.empty() && t.front() == '+') t.remove_prefix(1);
  double v = 0;
  const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), v);
  // Out of range: 1e999 is read as infinity (load_cloud drops non-finite points), 1e-999 as 0.
  if (ec == std::errc::result_out_of_range && end == t.data() + t.size()) {
    const auto e = t.find_first_of("eE");
    const bool underflow = e != std::string_view::npos && e + 1 < t.size() && t[e + 1] == '-';
    v = underflow ? 0.0 : std::numeric_limits<double>::infinity();
    if (t.front() == '-') v = -v;
  } else if (ec != std::errc() || end != t.data() + t.size())
    return false;
  const T x = static_cast<T>(v);
  std::memcpy(out, &x, sizeof x);
  return true;
}

/// Parses one ASCII value of `datatype` into `out`; false when it is not a number of that type.
bool store_value(std::string_view t, std::uint8_t datatype, std::uint8_t* out) {
  using F = pcl::PCLPointField;
  switch (datatype) {
    case F::INT8: return store_int<std::int8_t>(t, out);
    case F::UINT8: return store_int<std::uint8_t>(t, out);
    case F::INT16: return store_int<std::int16_t>(t, out);
    case F::UINT16: return store_int<std::uint16_t>(t, out);
    case F::INT32: return store_int<std::int32_t>(t, out);
    case F::UINT32: return store_int<std::uint32_t>(t, out);
    case F::INT64: return store_int<std::int64_t>(t, out);
    case F::UINT64: return store_int<std::uint64_t>(t, out);
    case F::FLOAT32: return store_float<float>(t, out);
    case F::FLOAT64: return store_float<double>(t, out);
    default: return false;
  }
}

struct Header {
  std::vector<std::string> fields;
  std::vector<std::uint64_t> sizes, counts;
  std::vector<char> types;
  std::optional<std::uint64_t> width, height, points;
  std::string data;           // ascii, binary or binary_compressed
  std::size_t data_start = 0;  // byte offset of the point data
  std::size_t data_line = 0;   // 1-based line number of the first data line (ascii)
};

Header parse_header(const std::string& bytes, const std::string& name) {
  Header h;
  std::size_t pos = 0;
  std::size_t line_no = 0;
  std::vector<std::string> seen;
  auto fail = [&](const std::string& what) -> UserError {
    return UserError(name + ": PCD header, line " + std::to_string(line_no) + ": " + what);
  };
  while (h.data.empty()) {
    if (pos >= bytes.size() || pos > kMaxHeaderBytes)
      throw UserError(name + ": no PCD header (no DATA line" +
                      (pos > kMaxHeaderBytes ? " in the first " + std::to_string(kMaxHeaderBytes) + " bytes" : std::string()) +
                      "): not a PCD file, or truncated");
    std::size_t end = bytes.find('\n', pos);
    if (end == std::string::npos) end = bytes.size();
    std::string_view line(bytes.data() + pos, end - pos);
    pos = end + 1;
    ++line_no;
    if (line.size() > kMaxHeaderLine) throw fail("a line of " + std::to_string(line.size()) + " bytes: not a PCD file, or corrupt");
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    if (std::any_of(line.begin(), line.end(), [](char c) { return static_cast<unsigned char>(c) < 0x20 && c != '\t'; }))
      throw fail("'" + shown(line) + "' has binary bytes: not a PCD file, or corrupt");
    const auto words = split(line);
    if (words.empty() || words[0].front() == '#') continue;
    const std::string key(words[0]);
    const std::vector<std::string_view> values(words.begin() + 1, words.end());
    static const std::vector<std::string> keys = {"VERSION", "FIELDS", "COLUMNS", "SIZE",   "TYPE",
                                                   "COUNT",   "WIDTH",  "HEIGHT",  "VIEWPOINT", "POINTS", "DATA"};
    if (std::find(keys.begin(), keys.end(), key) == keys.end())
      throw fail("unknown line '" + shown(line) + "' (a PCD header has VERSION, FIELDS, SIZE, TYPE, COUNT, WIDTH, "
                 "HEIGHT, VIEWPOINT, POINTS and DATA lines): not a PCD file, or corrupt");
    const std::string canonical = key == "COLUMNS" ? "FIELDS" : key;
    if (std::find(seen.begin(), seen.end(), canonical) != seen.end()) throw fail("a second " + canonical + " line");
    seen.push_back(canonical);
    if (canonical == "VERSION" || canonical == "VIEWPOINT") continue;
    if (values.empty()) throw fail(key + " without a value");
    if (canonical == "FIELDS") {
      for (const auto v : values) h.fields.emplace_back(v);
    } else if (canonical == "SIZE" || canonical == "COUNT") {
      auto& out = canonical == "SIZE" ? h.sizes : h.counts;
      for (const auto v : values) {
        const auto n = parse_uint(v);
        if (!n) throw fail(key + " value '" + shown(v) + "' is not a whole number");
        out.push_back(*n);
      }
    } else if (canonical == "TYPE") {
      for (const auto v : values) {
        const char t = v.size() == 1 ? static_cast<char>(std::toupper(static_cast<unsigned char>(v[0]))) : '?';
        if (t != 'I' && t != 'U' && t != 'F' && t != 'B') throw fail("TYPE value '" + shown(v) + "' is not I, U, F or B");
        h.types.push_back(t);
      }
    } else if (canonical == "WIDTH" || canonical == "HEIGHT" || canonical == "POINTS") {
      const auto n = parse_uint(values[0]);
      if (!n || *n > std::numeric_limits<std::uint32_t>::max() || values.size() != 1)
        throw fail(key + " '" + shown(line.substr(static_cast<std::size_t>(values[0].data() - line.data()))) +
                   "' is not one whole number up to " +
                   std::to_string(std::numeric_limits<std::uint32_t>::max()));
      (canonical == "WIDTH" ? h.width : canonical == "HEIGHT" ? h.height : h.points) = *n;
    } else {  // DATA
      h.data = std::string(values[0]);
      if (h.data != "ascii" && h.data != "binary" && h.data != "binary_compressed")
        throw fail("DATA '" + shown(values[0]) + "' is not ascii, binary or binary_compressed");
    }
  }
  h.data_start = std::min(pos, bytes.size());
  h.data_line = line_no + 1;

  // The four per-field lines must describe the same fields.
  auto fail_fields = [&](const std::string& what) -> UserError {
    return UserError(name + ": PCD header: " + what + " (FIELDS, SIZE, TYPE and COUNT list one value per field)");
  };
  if (h.fields.empty()) throw fail_fields("no FIELDS line");
  const std::size_t n = h.fields.size();
  if (h.sizes.empty() && h.types.empty()) {  // PCD .5 files may have neither: every field is F 4
    h.sizes.assign(n, 4);
    h.types.assign(n, 'F');
  }
  if (h.sizes.size() != n) throw fail_fields("FIELDS names " + std::to_string(n) + " fields, SIZE gives " + std::to_string(h.sizes.size()));
  if (h.types.size() != n) throw fail_fields("FIELDS names " + std::to_string(n) + " fields, TYPE gives " + std::to_string(h.types.size()));
  if (h.counts.empty()) h.counts.assign(n, 1);  // COUNT is optional (PCD .5)
  if (h.counts.size() != n) throw fail_fields("FIELDS names " + std::to_string(n) + " fields, COUNT gives " + std::to_string(h.counts.size()));
  for (std::size_t i = 0; i < n; ++i) {
    if (datatype_of(h.types[i], h.sizes[i]) == 0)
      throw fail_fields("field '" + shown(h.fields[i]) + "' has TYPE " + h.types[i] + " with SIZE " + std::to_string(h.sizes[i]) +
                        " (I and U take 1, 2, 4 or 8 bytes, F takes 4 or 8, B takes 1)");
    if (h.counts[i] == 0 || h.counts[i] > kMaxCount)
      throw fail_fields("field '" + shown(h.fields[i]) + "' has COUNT " + std::to_string(h.counts[i]) + " (1 to " +
                        std::to_string(kMaxCount) + ")");
  }
  // WIDTH x HEIGHT and POINTS: either may stand for the other (PCD .5 files have only POINTS).
  if (!h.width && !h.points) throw UserError(name + ": PCD header: neither WIDTH nor POINTS says how many points there are");
  if (!h.height) h.height = 1;
  if (!h.width) h.width = *h.points / std::max<std::uint64_t>(*h.height, 1);
  const std::uint64_t wh = *h.width * *h.height;
  if (!h.points) h.points = wh;
  if (wh != *h.points)
    throw UserError(name + ": PCD header: WIDTH x HEIGHT (" + std::to_string(*h.width) + " x " + std::to_string(*h.height) +
                    " = " + std::to_string(wh) + ") and POINTS (" + std::to_string(*h.points) + ") disagree");
  return h;
}

}  // namespace

pcl::PCLPointCloud2 parse_pcd(const std::string& bytes, const std::string& name) {
  const Header h = parse_header(bytes, name);
  pcl::PCLPointCloud2 blob;
  std::uint64_t step = 0;
  std::uint64_t values_per_point = 0;
  for (std::size_t i = 0; i < h.fields.size(); ++i) {
    pcl::PCLPointField f;
    f.name = h.fields[i];
    f.offset = static_cast<std::uint32_t>(step);
    f.datatype = datatype_of(h.types[i], h.sizes[i]);
    f.count = static_cast<std::uint32_t>(h.counts[i]);
    blob.fields.push_back(f);
    step += h.sizes[i] * h.counts[i];  // <= 8 * 2^16 per field
    values_per_point += h.counts[i];
  }
  if (step > std::numeric_limits<std::uint32_t>::max() / 2)
    throw UserError(name + ": PCD header: a point of " + std::to_string(step) + " bytes is implausible");
  const std::uint64_t n = *h.points;
  const std::uint64_t available = bytes.size() - h.data_start;
  blob.width = static_cast<std::uint32_t>(*h.width);
  blob.height = static_cast<std::uint32_t>(*h.height);
  blob.point_step = static_cast<std::uint32_t>(step);
  blob.row_step = static_cast<std::uint32_t>(std::min<std::uint64_t>(*h.width * step, std::numeric_limits<std::uint32_t>::max()));
  blob.is_dense = false;
  if (n == 0) return blob;
  if (static_cast<std::uint64_t>(*h.width) * step > std::numeric_limits<std::uint32_t>::max())
    throw UserError(name + ": PCD header: a row of " + std::to_string(*h.width) + " points of " + std::to_string(step) +
                    " bytes is implausible");
  auto too_short = [&](std::uint64_t needed, const std::string& of) {
    return UserError(name + ": the header announces " + std::to_string(*h.width) + " x " + std::to_string(*h.height) +
                     " points of " + std::to_string(step) + " bytes (" + (of.empty() ? std::string() : of + " ") + "at least " + std::to_string(needed) +
                     " bytes), the file holds " + std::to_string(available) + " bytes of point data (truncated or corrupt)");
  };
  constexpr std::uint64_t kHuge = std::numeric_limits<std::uint64_t>::max() / 4;
  const UserError too_many(name + ": the header announces " + std::to_string(*h.width) + " x " + std::to_string(*h.height) +
                           " points of " + std::to_string(step) + " bytes: more than any file could hold (corrupt header)");
  if (n > kHuge / step) throw too_many;
  const std::uint64_t total = n * step;

  if (h.data == "binary") {
    if (total > available) throw too_short(total, "");
    blob.data.assign(bytes.begin() + static_cast<std::ptrdiff_t>(h.data_start),
                     bytes.begin() + static_cast<std::ptrdiff_t>(h.data_start + total));
    return blob;
  }

  if (h.data == "binary_compressed") {
    // Two little-endian uint32 (compressed and uncompressed size), then LZF data holding the
    // fields one after another (all points' x, then all y, ...).
    if (available < 8) throw too_short(8, "sizes:");
    std::uint32_t compressed = 0, uncompressed = 0;
    std::memcpy(&compressed, bytes.data() + h.data_start, 4);
    std::memcpy(&uncompressed, bytes.data() + h.data_start + 4, 4);
    if (uncompressed != total)
      throw UserError(name + ": binary_compressed PCD: the data says it uncompresses to " + std::to_string(uncompressed) +
                      " bytes, the header's " + std::to_string(n) + " points of " + std::to_string(step) + " bytes need " +
                      std::to_string(total) + " (corrupt)");
    if (compressed > available - 8)
      throw UserError(name + ": binary_compressed PCD: the data says it holds " + std::to_string(compressed) +
                      " compressed bytes, the file has " + std::to_string(available - 8) + " (truncated or corrupt)");
    if (total > static_cast<std::uint64_t>(compressed) * kMaxLzfRatio)
      throw UserError(name + ": binary_compressed PCD: " + std::to_string(compressed) + " compressed bytes cannot hold the " +
                      std::to_string(total) + " bytes the header's points need (LZF expands at most ~90 times; corrupt)");
    std::vector<std::uint8_t> soa(total);
    const unsigned got = pcl::lzfDecompress(bytes.data() + h.data_start + 8, compressed, soa.data(), uncompressed);
    if (got != uncompressed)
      throw UserError(name + ": binary_compressed PCD: the compressed data is corrupt (it gave " + std::to_string(got) +
                      " of " + std::to_string(uncompressed) + " bytes)");
    blob.data.resize(total);
    std::uint64_t field_start = 0;
    for (std::size_t i = 0; i < blob.fields.size(); ++i) {
      const std::uint64_t fs = h.sizes[i] * h.counts[i];
      for (std::uint64_t p = 0; p < n; ++p)
        std::memcpy(blob.data.data() + p * step + blob.fields[i].offset, soa.data() + field_start + p * fs, fs);
      field_start += fs * n;
    }
    return blob;
  }

  // ascii: one point per line, its values separated by spaces or tabs. Every value takes a
  // character and a separator at least: check that before allocating the points.
  if (n > kHuge / (2 * values_per_point)) throw too_many;
  if (n * values_per_point * 2 > available + 1) throw too_short(n * values_per_point * 2, "as text");
  blob.data.assign(total, 0);
  std::size_t pos = h.data_start;
  std::size_t line_no = h.data_line - 1;
  std::uint64_t read = 0;
  std::vector<std::string_view> words;
  while (read < n && pos < bytes.size()) {
    std::size_t end = bytes.find('\n', pos);
    if (end == std::string::npos) end = bytes.size();
    std::string_view line(bytes.data() + pos, end - pos);
    pos = end + 1;
    ++line_no;
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    words = split(line, values_per_point + 1);
    if (words.empty()) continue;
    if (words.size() != values_per_point)
      throw UserError(name + ", line " + std::to_string(line_no) + ": " +
                      (words.size() > values_per_point ? "more than " + std::to_string(values_per_point) : std::to_string(words.size())) +
                      " values, the header's fields need " + std::to_string(values_per_point) + " per point");
    std::uint8_t* out = blob.data.data() + read * step;
    std::size_t w = 0;
    for (std::size_t i = 0; i < blob.fields.size(); ++i)
      for (std::uint64_t c = 0; c < h.counts[i]; ++c, ++w, out += h.sizes[i])
        if (!store_value(words[w], blob.fields[i].datatype, out))
          throw UserError(name + ", line " + std::to_string(line_no) + ": field '" + shown(h.fields[i]) + "' value '" +
                          shown(words[w]) + "' is not a number of TYPE " + h.types[i] + " SIZE " + std::to_string(h.sizes[i]));
    ++read;
  }
  if (read < n)
    throw UserError(name + ": the header announces " + std::to_string(n) + " points, the file holds " + std::to_string(read) +
                    " (truncated or corrupt)");
  return blob;
}

namespace {

std::string read_file(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  std::error_code ec;
  const auto size = std::filesystem::file_size(file, ec);
  if (!in || ec) throw UserError(file.string() + ": cannot open (check it exists and is readable)");
  std::string bytes(size, '\0');
  in.read(bytes.data(), static_cast<std::streamsize>(size));
  if (static_cast<std::uintmax_t>(in.gcount()) != size) throw UserError(file.string() + ": read error (the file changed while it was read?)");
  return bytes;
}

// ---- PLY

struct PlyProperty {
  std::string name;
  std::uint8_t type = 0;        // PCLPointField datatype of the value (of the items, for a list)
  std::uint8_t count_type = 0;  // a list's count type, 0 for a scalar
  std::size_t line = 0;         // where the header declares it
};

struct PlyElement {
  std::string name;
  std::uint64_t count = 0;
  std::vector<PlyProperty> properties;
};

std::uint8_t ply_datatype(const std::string& t) {
  using F = pcl::PCLPointField;
  if (t == "char" || t == "int8") return F::INT8;
  if (t == "uchar" || t == "uint8") return F::UINT8;
  if (t == "short" || t == "int16") return F::INT16;
  if (t == "ushort" || t == "uint16") return F::UINT16;
  if (t == "int" || t == "int32") return F::INT32;
  if (t == "uint" || t == "uint32") return F::UINT32;
  if (t == "float" || t == "float32") return F::FLOAT32;
  if (t == "double" || t == "float64") return F::FLOAT64;
  return 0;
}

/// A list count read as a whole number, or nothing when it is negative or not whole.
std::optional<std::uint64_t> count_value(const std::uint8_t* p, std::uint8_t datatype) {
  using F = pcl::PCLPointField;
  std::int64_t v = 0;
  switch (datatype) {
    case F::INT8: { std::int8_t x; std::memcpy(&x, p, 1); v = x; break; }
    case F::UINT8: { std::uint8_t x; std::memcpy(&x, p, 1); v = x; break; }
    case F::INT16: { std::int16_t x; std::memcpy(&x, p, 2); v = x; break; }
    case F::UINT16: { std::uint16_t x; std::memcpy(&x, p, 2); v = x; break; }
    case F::INT32: { std::int32_t x; std::memcpy(&x, p, 4); v = x; break; }
    case F::UINT32: { std::uint32_t x; std::memcpy(&x, p, 4); v = x; break; }
    default: return std::nullopt;  // a float count
  }
  if (v < 0) return std::nullopt;
  return static_cast<std::uint64_t>(v);
}

struct PlyHeader {
  std::string format;  // ascii, binary_little_endian, binary_big_endian
  std::vector<PlyElement> elements;
  std::size_t data_start = 0;
  std::size_t data_line = 0;
};

PlyHeader parse_ply_header(const std::string& bytes, const std::string& name) {
  PlyHeader h;
  std::size_t pos = 0;
  std::size_t line_no = 0;
  auto next_line = [&]() -> std::optional<std::string_view> {
    if (pos >= bytes.size() || pos > kMaxHeaderBytes) return std::nullopt;
    std::size_t end = bytes.find('\n', pos);
    if (end == std::string::npos) end = bytes.size();
    std::string_view line(bytes.data() + pos, end - pos);
    pos = end + 1;
    ++line_no;
    if (line.size() > kMaxHeaderLine)
      throw UserError(name + ": the PLY header, line " + std::to_string(line_no) + ": a line of " + std::to_string(line.size()) +
                      " bytes: not a PLY file, or corrupt");
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    return line;
  };
  const auto first = next_line();
  if (!first || *first != "ply") throw UserError(name + ": not a PLY file (it does not start with a line 'ply')");
  auto fail = [&](const std::string& what) {
    return UserError(name + ": the PLY header, line " + std::to_string(line_no) + ": " + what);
  };
  bool complete = false;
  while (const auto line = next_line()) {
    if (std::any_of(line->begin(), line->end(), [](char c) { return static_cast<unsigned char>(c) < 0x20 && c != '\t'; }))
      throw fail("'" + shown(*line) + "' has binary bytes: not a PLY file, or corrupt");
    const auto words = split(*line);
    if (words.empty()) continue;
    const std::string key(words[0]);
    if (key == "comment" || key == "obj_info") continue;
    if (key == "end_header") {
      complete = true;
      break;
    }
    if (key == "format") {
      if (!h.format.empty()) throw fail("a second format line");
      h.format = words.size() > 1 ? std::string(words[1]) : std::string();
      if (h.format != "ascii" && h.format != "binary_little_endian" && h.format != "binary_big_endian")
        throw fail("format '" + shown(h.format) + "' is not ascii, binary_little_endian or binary_big_endian");
    } else if (key == "element") {
      const std::string element = words.size() > 1 ? std::string(words[1]) : std::string();
      const std::string_view t = words.size() > 2 ? words[2] : std::string_view();
      const auto n = parse_uint(t);
      if (element.empty() || !n) throw fail("element '" + shown(element) + "' has count '" + shown(t) + "', not a whole number");
      if (words.size() != 3) throw fail("'" + shown(*line) + "' is not 'element NAME COUNT'");
      h.elements.push_back(PlyElement{element, *n, {}});
    } else if (key == "property") {
      if (h.elements.empty()) throw fail("property '" + shown(*line) + "' comes before any element");
      PlyProperty p;
      p.line = line_no;
      const bool list = words.size() > 1 && words[1] == "list";
      if (list && words.size() == 5) {
        p.count_type = ply_datatype(std::string(words[2]));
        p.type = ply_datatype(std::string(words[3]));
        p.name = std::string(words[4]);
      } else if (!list && words.size() == 3) {
        p.type = ply_datatype(std::string(words[1]));
        p.name = std::string(words[2]);
      }
      const bool integer_count = p.count_type != 0 && p.count_type != pcl::PCLPointField::FLOAT32 &&
                                 p.count_type != pcl::PCLPointField::FLOAT64;
      if (p.name.empty())
        throw fail("'" + shown(*line) + "' is not 'property TYPE NAME' or 'property list COUNT_TYPE TYPE NAME'");
      // An unknown type is refused when the reader needs the property: in the vertex element or
      // an element before it (checked in parse_ply); elements after the vertices are not read.
      if (list && !integer_count) p.type = 0;
      h.elements.back().properties.push_back(p);
    } else {
      throw fail("unknown line '" + shown(*line) + "': not a PLY file, or corrupt");
    }
  }
  if (!complete)
    throw UserError(name + ": no PLY header (no end_header line" +
                    (pos > kMaxHeaderBytes ? " in the first " + std::to_string(kMaxHeaderBytes) + " bytes" : std::string()) +
                    "): not a PLY file, or truncated");
  if (h.format.empty()) throw UserError(name + ": the PLY header has no format line");
  h.data_start = std::min(pos, bytes.size());
  h.data_line = line_no + 1;
  return h;
}

/// Which value a PLY reader is at, for messages (built only when one is needed).
struct Where {
  const std::string& element;
  std::uint64_t index;
  const std::string& property;
  [[nodiscard]] std::string str() const {
    return element + " " + std::to_string(index) + " property '" + shown(property) + "'";
  }
};

/// Walks the data of a PLY file: ASCII as whitespace-separated tokens (counting lines for the
/// messages), binary as bytes with the file's byte order.
class PlyData {
 public:
  PlyData(const std::string& bytes, const PlyHeader& h, const std::string& name)
      : bytes_(bytes), pos_(h.data_start), line_(h.data_line), ascii_(h.format == "ascii"),
        swap_(h.format == "binary_big_endian"), name_(name) {}

  [[nodiscard]] std::uint64_t remaining() const { return bytes_.size() - std::min(pos_, bytes_.size()); }

  /// Reads one value of `datatype` into out (native byte order); `what` names it for messages.
  void value(std::uint8_t datatype, std::uint8_t* out, const Where& what) {
    if (ascii_) {
      const auto t = token(what);
      if (!store_value(t, datatype, out))
        throw UserError(name_ + ", line " + std::to_string(line_) + ": " + what.str() + " '" + shown(t) + "' is not a number of its type");
      return;
    }
    const std::size_t n = pcl::getFieldSize(datatype);
    if (remaining() < n) throw truncated(what);
    std::memcpy(out, bytes_.data() + pos_, n);
    if (swap_) std::reverse(out, out + n);
    pos_ += n;
  }

  /// Skips one property (a scalar, or a list with its items).
  void skip(const PlyProperty& p, const Where& what) {
    if (p.count_type == 0) {
      skip_values(p.type, 1, what);
      return;
    }
    std::uint8_t buf[8] = {};
    value(p.count_type, buf, what);
    const auto n = count_value(buf, p.count_type);
    if (!n)
      throw UserError(name_ + (ascii_ ? ", line " + std::to_string(line_) : std::string()) + ": " + what.str() +
                      " has a negative list count (corrupt)");
    skip_values(p.type, *n, what);
  }

  [[nodiscard]] UserError truncated(const Where& what) const {
    return UserError(name_ + ": the file ends before " + what.str() + " (truncated or corrupt)");
  }

 private:
  void skip_values(std::uint8_t datatype, std::uint64_t n, const Where& what) {
    if (ascii_) {
      for (std::uint64_t i = 0; i < n; ++i) (void)token(what);
      return;
    }
    const std::uint64_t size = pcl::getFieldSize(datatype);
    if (n > remaining() / size) throw truncated(what);
    pos_ += n * size;
  }

  std::string_view token(const Where& what) {
    while (pos_ < bytes_.size() && (bytes_[pos_] == ' ' || bytes_[pos_] == '\t' || bytes_[pos_] == '\r' || bytes_[pos_] == '\n')) {
      if (bytes_[pos_] == '\n') ++line_;
      ++pos_;
    }
    const std::size_t start = pos_;
    while (pos_ < bytes_.size() && bytes_[pos_] != ' ' && bytes_[pos_] != '\t' && bytes_[pos_] != '\r' && bytes_[pos_] != '\n') ++pos_;
    if (pos_ == start) throw truncated(what);
    return std::string_view(bytes_.data() + start, pos_ - start);
  }

  const std::string& bytes_;
  std::size_t pos_;
  std::size_t line_;
  bool ascii_;
  bool swap_;
  const std::string& name_;
};

}  // namespace

pcl::PCLPointCloud2 parse_ply(const std::string& bytes, const std::string& name) {
  const PlyHeader h = parse_ply_header(bytes, name);
  const auto vertex = std::find_if(h.elements.begin(), h.elements.end(), [](const auto& e) { return e.name == "vertex"; });
  if (vertex == h.elements.end()) throw UserError(name + ": the PLY file has no vertex element");
  for (auto e = h.elements.begin(); e != vertex + 1; ++e)
    for (const auto& p : e->properties)
      if (p.type == 0)
        throw UserError(name + ": the PLY header, line " + std::to_string(p.line) + ": property '" + shown(p.name) + "' of element '" +
                        shown(e->name) + "' has an unknown type (char, uchar, short, ushort, int, uint, float, double or their "
                        "sized names; a list's count an integer type)");
  if (vertex->count > std::numeric_limits<std::uint32_t>::max())
    throw UserError(name + ": the PLY header claims " + std::to_string(vertex->count) + " vertices (at most " +
                    std::to_string(std::numeric_limits<std::uint32_t>::max()) + ")");
  PlyData data(bytes, h, name);
  // Elements before the vertices (rare) are skipped, each checked against the file as it goes.
  for (auto e = h.elements.begin(); e != vertex; ++e)
    for (std::uint64_t i = 0; i < e->count && !e->properties.empty(); ++i)
      for (const auto& p : e->properties) data.skip(p, Where{e->name, i, p.name});

  pcl::PCLPointCloud2 blob;
  std::uint64_t step = 0;
  std::uint64_t min_bytes = 0;  // the fewest bytes one vertex takes in the file
  const bool ascii = h.format == "ascii";
  for (const auto& p : vertex->properties) {
    min_bytes += ascii ? 2 : pcl::getFieldSize(p.count_type ? p.count_type : p.type);
    if (p.count_type) continue;
    pcl::PCLPointField f;
    f.name = p.name == "nx" ? "normal_x" : p.name == "ny" ? "normal_y" : p.name == "nz" ? "normal_z" : p.name;
    f.offset = static_cast<std::uint32_t>(step);
    f.datatype = p.type;
    f.count = 1;
    blob.fields.push_back(f);
    step += pcl::getFieldSize(p.type);
  }
  if (vertex->properties.size() > 4096)
    throw UserError(name + ": the PLY vertex element has " + std::to_string(vertex->properties.size()) + " properties (implausibly many)");
  if (std::none_of(vertex->properties.begin(), vertex->properties.end(), [](const auto& p) { return p.count_type == 0; }))
    throw UserError(name + ": the PLY vertex element has no scalar properties (x, y, z at least)");
  const std::uint64_t n = vertex->count;
  blob.width = static_cast<std::uint32_t>(n);
  blob.height = 1;
  blob.point_step = static_cast<std::uint32_t>(step);
  blob.row_step = static_cast<std::uint32_t>(std::min<std::uint64_t>(n * step, std::numeric_limits<std::uint32_t>::max()));
  blob.is_dense = false;
  if (n == 0) return blob;
  // Check the claimed count against the file before allocating for it.
  const std::uint64_t available = data.remaining();
  if (min_bytes > 0 && n > (available + 1) / min_bytes)
    throw UserError(name + ": the header claims " + std::to_string(n) + " vertices (at least " +
                    std::to_string(n > (1ULL << 62) / min_bytes ? (1ULL << 62) : n * min_bytes) +
                    " bytes) but the file holds " + std::to_string(available) + " bytes of data: truncated or corrupt");
  if (n * step > std::numeric_limits<std::uint32_t>::max())
    throw UserError(name + ": " + std::to_string(n) + " vertices of " + std::to_string(step) + " bytes are implausibly many");
  blob.data.assign(n * step, 0);
  for (std::uint64_t i = 0; i < n; ++i) {
    std::uint8_t* out = blob.data.data() + i * step;
    for (const auto& p : vertex->properties) {
      if (p.count_type) {
        data.skip(p, Where{vertex->name, i, p.name});
        continue;
      }
      data.value(p.type, out, Where{vertex->name, i, p.name});
      out += pcl::getFieldSize(p.type);
    }
  }
  return blob;
}

pcl::PCLPointCloud2 read_pcd(const std::filesystem::path& file) { return parse_pcd(read_file(file), file.string()); }

pcl::PCLPointCloud2 read_ply(const std::filesystem::path& file) { return parse_ply(read_file(file), file.string()); }

}  // namespace fettle::vision::detail
