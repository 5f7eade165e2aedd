// Fettle's own PCD reader (see pcd_reader.hpp for why).
#include "pcd_reader.hpp"

#include <algorithm>
#include <charconv>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <limits>
#include <optional>
#include <string_view>
#include <vector>

#include <pcl/io/lzf.h>

#include "fettle/core/error.hpp"

namespace fettle::vision::detail {

namespace {

constexpr std::size_t kMaxHeaderBytes = 1 << 20;  // a real header is a few hundred bytes
constexpr std::uint64_t kMaxCount = 1 << 16;      // values per field (FPFH has 33, VFH 308)
// LZF (binary_compressed) expands at most 88 times (a 3-byte back reference yields 264 bytes).
constexpr std::uint64_t kMaxLzfRatio = 100;

std::vector<std::string_view> split(std::string_view line) {
  std::vector<std::string_view> out;
  std::size_t i = 0;
  while (i < line.size()) {
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
        if (v.size() != 1 || (v[0] != 'I' && v[0] != 'U' && v[0] != 'F'))
          throw fail("TYPE value '" + shown(v) + "' is not I, U or F");
        h.types.push_back(v[0]);
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
  if (h.sizes.size() != n) throw fail_fields("FIELDS names " + std::to_string(n) + " fields, SIZE gives " + std::to_string(h.sizes.size()));
  if (h.types.size() != n) throw fail_fields("FIELDS names " + std::to_string(n) + " fields, TYPE gives " + std::to_string(h.types.size()));
  if (h.counts.empty()) h.counts.assign(n, 1);  // COUNT is optional (PCD .5)
  if (h.counts.size() != n) throw fail_fields("FIELDS names " + std::to_string(n) + " fields, COUNT gives " + std::to_string(h.counts.size()));
  for (std::size_t i = 0; i < n; ++i) {
    if (datatype_of(h.types[i], h.sizes[i]) == 0)
      throw fail_fields("field '" + shown(h.fields[i]) + "' has TYPE " + h.types[i] + " with SIZE " + std::to_string(h.sizes[i]) +
                        " (I and U take 1, 2, 4 or 8 bytes, F takes 4 or 8)");
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
  if (n > kHuge / step) throw too_short(kHuge, "");
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
    if (compressed > available - 8 || total > static_cast<std::uint64_t>(compressed) * kMaxLzfRatio)
      throw too_short(total, "uncompressed;");
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
  if (n > kHuge / (2 * values_per_point) || n * values_per_point * 2 > available + 1)
    throw too_short(n > kHuge / (2 * values_per_point) ? kHuge : n * values_per_point * 2, "as text");
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
    words = split(line);
    if (words.empty()) continue;
    if (words.size() != values_per_point)
      throw UserError(name + ", line " + std::to_string(line_no) + ": " + std::to_string(words.size()) +
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

pcl::PCLPointCloud2 read_pcd(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  if (!in) throw UserError(file.string() + ": cannot open (check it exists and is readable)");
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) throw UserError(file.string() + ": read error");
  return parse_pcd(bytes, file.string());
}

}  // namespace fettle::vision::detail
