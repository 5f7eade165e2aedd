// Banded, bricked signed-distance grid with trilinear interpolation (see sdf_grid.hpp).
#include "fettle/planning/sdf_grid.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <thread>

#include "fettle/core/atomic_file.hpp"

namespace fettle::planning {

namespace {

constexpr int kCells = 8;              ///< cells per brick edge
constexpr int kNodes = kCells + 1;     ///< lattice values per brick edge (one shared layer)
constexpr int kBrickValues = kNodes * kNodes * kNodes;
constexpr int kFlagWords = kCells * kCells * kCells / 64;
constexpr double kScale = 2000.0;      ///< band level: int16 units per mm (0.5 µm steps, ±16.38 mm)
constexpr double kFarScale = 500.0;    ///< far level: 2 µm steps, ±65.5 mm
/// The last byte is the file format's version: a cache of another version is rebuilt, never
/// read (test SdfGridCache.ACorruptOrTruncatedFileIsNeverTrusted). 3: settings with
/// kink_jump_mm, a checksum, and the key with FNV-1a's published offset basis.
constexpr std::array<char, 8> kMagic{'F', 'T', 'L', 'S', 'D', 'F', 'G', '3'};

/// FNV-1a, 64 bit (Fowler, Noll, Vo): offset basis 14695981039346656037, prime 1099511628211.
std::uint64_t fnv1a(const void* data, std::size_t n, std::uint64_t h = 0xcbf29ce484222325ULL) {
  const auto* b = static_cast<const unsigned char*>(data);
  for (std::size_t i = 0; i < n; ++i) h = (h ^ b[i]) * 0x100000001b3ULL;
  return h;
}

}  // namespace

namespace {

enum class Lookup { value, kink, uncovered };

/// One lattice: bricks of kCells³ cells over a box, allocated where the surface may be near.
struct Level {
  Vec3 origin = Vec3::Zero();  ///< lattice node (0, 0, 0)
  double voxel = 0.5, inv_voxel = 2.0;
  double scale = 2000.0;       ///< int16 units per mm
  std::int64_t nbx = 0, nby = 0, nbz = 0;  ///< bricks along x, y, z
  std::vector<std::int32_t> brick_of;      ///< per brick slot: index into values / flags, or -1
  std::vector<std::int16_t> values;        ///< kBrickValues per brick, x fastest
  std::vector<std::uint64_t> flags;        ///< kFlagWords per brick: cell answered exactly
  std::uint64_t exact_cells = 0;

  /// `same_sign`, when given, says for a kink cell whether its eight corners all have the
  /// sign of the interpolated value.
  [[nodiscard]] Lookup lattice(const Vec3& p, double& out, bool* same_sign = nullptr) const {
    const Vec3 q = (p - origin) * inv_voxel;
    const double fx = std::floor(q.x()), fy = std::floor(q.y()), fz = std::floor(q.z());
    if (!(fx >= 0.0 && fy >= 0.0 && fz >= 0.0)) return Lookup::uncovered;  // also NaN
    const auto ix = static_cast<std::int64_t>(fx), iy = static_cast<std::int64_t>(fy), iz = static_cast<std::int64_t>(fz);
    const std::int64_t bx = ix / kCells, by = iy / kCells, bz = iz / kCells;
    if (bx >= nbx || by >= nby || bz >= nbz) return Lookup::uncovered;
    const std::int32_t b = brick_of[static_cast<std::size_t>((bz * nby + by) * nbx + bx)];
    if (b < 0) return Lookup::uncovered;
    const int cx = static_cast<int>(ix - bx * kCells), cy = static_cast<int>(iy - by * kCells),
              cz = static_cast<int>(iz - bz * kCells);
    const int cell = (cz * kCells + cy) * kCells + cx;
    const std::int16_t* v = values.data() + static_cast<std::size_t>(b) * kBrickValues + (cz * kNodes + cy) * kNodes + cx;
    const double tx = q.x() - fx, ty = q.y() - fy, tz = q.z() - fz;
    constexpr int dy = kNodes, dz = kNodes * kNodes;
    const double c00 = v[0] + tx * (v[1] - v[0]);
    const double c10 = v[dy] + tx * (v[dy + 1] - v[dy]);
    const double c01 = v[dz] + tx * (v[dz + 1] - v[dz]);
    const double c11 = v[dz + dy] + tx * (v[dz + dy + 1] - v[dz + dy]);
    const double c0 = c00 + ty * (c10 - c00), c1 = c01 + ty * (c11 - c01);
    out = (c0 + tz * (c1 - c0)) / scale;
    const bool kink =
        (flags[static_cast<std::size_t>(b) * kFlagWords + static_cast<std::size_t>(cell >> 6)] >> (cell & 63)) & 1U;
    if (!kink) return Lookup::value;
    if (same_sign != nullptr) {
      const std::int16_t lo = std::min({v[0], v[1], v[dy], v[dy + 1], v[dz], v[dz + 1], v[dz + dy], v[dz + dy + 1]});
      const std::int16_t hi = std::max({v[0], v[1], v[dy], v[dy + 1], v[dz], v[dz + 1], v[dz + dy], v[dz + dy + 1]});
      *same_sign = out > 0 ? lo > 0 : hi < 0;
    }
    return Lookup::kink;
  }

  /// How far an interpolated value can be from the exact function anywhere in a cell: a
  /// distance changes by at most the distance moved, so the trilinear blend of the corners is
  /// within half the cell's diagonal, plus the sampled function's own jumps.
  [[nodiscard]] double kink_bound(double jump_mm) const { return 0.5 * std::sqrt(3.0) * voxel + jump_mm; }

  [[nodiscard]] std::size_t memory() const {
    return values.size() * sizeof(std::int16_t) + flags.size() * sizeof(std::uint64_t) +
           brick_of.size() * sizeof(std::int32_t);
  }
};

template <class Fn>
void parallel_for(std::size_t n, int threads, const Fn& fn) {
  std::atomic<std::size_t> next{0};
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t)
    pool.emplace_back([&] {
      for (std::size_t i = next++; i < n; i = next++) fn(i);
    });
  for (std::size_t i = next++; i < n; i = next++) fn(i);
  for (auto& th : pool) th.join();
}

/// Evaluates `exact` on a level over [box_min, box_max] grown by `band`, keeping the bricks
/// the surface may be within `band` of, flagging cells interpolated worse than `tol` at their
/// centre (or holding a value beyond the int16 range).
Level build_level(const SignedDistance& exact, const Vec3& box_min, const Vec3& box_max, double voxel, double band,
                  double tol, double scale, int threads, const SdfGrid::Progress& progress, const char* name) {
  Level L;
  L.voxel = voxel;
  L.inv_voxel = 1.0 / voxel;
  L.scale = scale;
  const double margin = band + voxel;
  L.origin = box_min - Vec3::Constant(margin);
  const Vec3 extent = box_max + Vec3::Constant(margin) - L.origin;
  const double brick_mm = kCells * voxel;
  L.nbx = std::max<std::int64_t>(1, static_cast<std::int64_t>(std::ceil(extent.x() / brick_mm)));
  L.nby = std::max<std::int64_t>(1, static_cast<std::int64_t>(std::ceil(extent.y() / brick_mm)));
  L.nbz = std::max<std::int64_t>(1, static_cast<std::int64_t>(std::ceil(extent.z() / brick_mm)));
  const auto slots = static_cast<std::size_t>(L.nbx * L.nby * L.nbz);
  L.brick_of.assign(slots, -1);
  auto brick_corner = [&](std::size_t s) {
    const auto bx = static_cast<std::int64_t>(s) % L.nbx, by = (static_cast<std::int64_t>(s) / L.nbx) % L.nby,
               bz = static_cast<std::int64_t>(s) / (L.nbx * L.nby);
    return Vec3(L.origin + brick_mm * Vec3(static_cast<double>(bx), static_cast<double>(by), static_cast<double>(bz)));
  };
  // Which bricks: the exact distance at the brick's centre says whether the surface can be
  // within the band of any point of it (half a diagonal away, plus a cell for a distance that
  // is short by up to a sample spacing off the sampled patch).
  const double reach = band + 0.5 * std::sqrt(3.0) * brick_mm + voxel;
  std::vector<std::uint8_t> keep(slots, 0);
  parallel_for(slots, threads, [&](std::size_t s) {
    keep[s] = std::abs(exact(brick_corner(s) + Vec3::Constant(0.5 * brick_mm))) <= reach ? 1 : 0;
  });
  std::vector<std::size_t> chosen;
  for (std::size_t s = 0; s < slots; ++s)
    if (keep[s] != 0) {
      L.brick_of[s] = static_cast<std::int32_t>(chosen.size());
      chosen.push_back(s);
    }
  L.values.assign(chosen.size() * kBrickValues, 0);
  L.flags.assign(chosen.size() * kFlagWords, 0);
  std::atomic<std::uint64_t> exact_cells{0};
  std::atomic<std::size_t> done{0};
  std::size_t reported = 0;
  const auto main_thread = std::this_thread::get_id();  // progress is reported from the caller's thread
  const double max_value = std::numeric_limits<std::int16_t>::max() / scale;
  parallel_for(chosen.size(), threads, [&](std::size_t b) {
    const Vec3 corner = brick_corner(chosen[b]);
    std::int16_t* v = L.values.data() + b * kBrickValues;
    std::uint64_t* f = L.flags.data() + b * kFlagWords;
    std::array<bool, kBrickValues> clipped{};
    for (int k = 0; k < kNodes; ++k)
      for (int j = 0; j < kNodes; ++j)
        for (int i = 0; i < kNodes; ++i) {
          const double e = exact(corner + voxel * Vec3(i, j, k));
          const int n = (k * kNodes + j) * kNodes + i;
          clipped[static_cast<std::size_t>(n)] = !(std::abs(e) < max_value);
          v[n] = static_cast<std::int16_t>(std::lround(std::clamp(e, -max_value, max_value) * scale));
        }
    std::uint64_t flagged = 0;
    for (int k = 0; k < kCells; ++k)
      for (int j = 0; j < kCells; ++j)
        for (int i = 0; i < kCells; ++i) {
          const int n0 = (k * kNodes + j) * kNodes + i;
          bool bad = false;
          double mean = 0.0;
          for (int c = 0; c < 8; ++c) {
            const int n = n0 + (c & 1) + ((c >> 1) & 1) * kNodes + ((c >> 2) & 1) * kNodes * kNodes;
            bad = bad || clipped[static_cast<std::size_t>(n)];
            mean += v[n];
          }
          mean /= 8.0 * scale;  // trilinear at the centre: the corners' mean
          if (!bad) bad = std::abs(mean - exact(corner + voxel * Vec3(i + 0.5, j + 0.5, k + 0.5))) > tol;
          if (bad) {
            const int cell = (k * kCells + j) * kCells + i;
            f[cell >> 6] |= std::uint64_t{1} << (cell & 63);
            ++flagged;
          }
        }
    exact_cells += flagged;
    const std::size_t now = ++done;
    if (progress && std::this_thread::get_id() == main_thread && now >= reported + std::max<std::size_t>(1, chosen.size() / 10)) {
      reported = now;
      progress(name, now, chosen.size());
    }
  });
  if (progress) progress(name, chosen.size(), chosen.size());
  L.exact_cells = exact_cells;
  return L;
}

}  // namespace

struct SdfGrid::Data {
  SdfGridSettings settings;
  SdfGridStats stats;
  SignedDistance exact;
  std::array<Level, 2> levels;  ///< band (fine), far (coarse, out to far_band_mm)

  /// The first level covering p answers it: its interpolated value, or nullopt where that
  /// cell is a kink (the exact function answers) or no level covers p.
  [[nodiscard]] std::optional<double> interpolated(const Vec3& p) const {
    double v = 0.0;
    for (const auto& level : levels) switch (level.lattice(p, v)) {
        case Lookup::value: return v;
        case Lookup::kink: return std::nullopt;
        case Lookup::uncovered: break;
      }
    return std::nullopt;
  }
  [[nodiscard]] double at(const Vec3& p) const {
    const auto v = interpolated(p);
    return v ? *v : exact(p);
  }
  /// As at(), but a kink cell whose interpolated value is beyond near_mm by more than the
  /// cell's bound, with all eight corners of its sign, answers with that value (the exact
  /// distance is beyond near_mm too). Mixed corner signs (a sign flip of the sampled function:
  /// an open border, the depth where it turns to +search) go to the exact function.
  [[nodiscard]] double near(const Vec3& p, double near_mm) const {
    double v = 0.0;
    bool same_sign = false;
    for (const auto& level : levels) switch (level.lattice(p, v, &same_sign)) {
        case Lookup::value: return v;
        case Lookup::kink:
          return same_sign && std::abs(v) > near_mm + level.kink_bound(settings.kink_jump_mm) ? v : exact(p);
        case Lookup::uncovered: break;
      }
    return exact(p);
  }
  void update_stats() {
    stats.bricks = levels[0].values.size() / kBrickValues;
    stats.brick_slots = levels[0].brick_of.size();
    stats.far_bricks = levels[1].values.size() / kBrickValues;
    stats.exact_cells = levels[0].exact_cells;
    stats.far_exact_cells = levels[1].exact_cells;
    stats.memory_bytes = levels[0].memory() + levels[1].memory();
  }
};

SdfGrid SdfGrid::build(SignedDistance exact, const Vec3& box_min, const Vec3& box_max, const SdfGridSettings& settings,
                       const Progress& progress) {
  const auto t0 = std::chrono::steady_clock::now();
  auto d = std::make_shared<Data>();
  d->settings = settings;
  auto& s = d->settings;
  if (!(s.voxel_mm > 0)) s.voxel_mm = 0.5;
  if (!(s.far_voxel_mm > 0)) s.far_voxel_mm = 4 * s.voxel_mm;
  if (!(s.kink_jump_mm >= 0 && std::isfinite(s.kink_jump_mm))) s.kink_jump_mm = SdfGridSettings{}.kink_jump_mm;
  s.far_band_mm = std::max(s.far_band_mm, s.band_mm);
  d->exact = std::move(exact);
  const int threads = s.threads > 0 ? s.threads : static_cast<int>(std::max(1U, std::thread::hardware_concurrency()));
  d->levels[0] = build_level(d->exact, box_min, box_max, s.voxel_mm, s.band_mm, s.exact_tol_mm, kScale, threads,
                             progress, "band");
  d->levels[1] = build_level(d->exact, box_min, box_max, s.far_voxel_mm, s.far_band_mm, s.far_tol_mm, kFarScale,
                             threads, progress, "far");
  d->update_stats();
  d->stats.build_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  SdfGrid g;
  g.data_ = std::move(d);
  return g;
}

double SdfGrid::operator()(const Vec3& p) const { return data_->at(p); }

std::optional<double> SdfGrid::interpolated(const Vec3& p) const { return data_->interpolated(p); }

SignedDistance SdfGrid::function() const {
  return {[d = data_](const Vec3& p) { return d->at(p); },
          [d = data_](const Vec3& p, double near_mm) { return d->near(p, near_mm); }};
}

const SdfGridStats& SdfGrid::stats() const { return data_->stats; }
const SdfGridSettings& SdfGrid::settings() const { return data_->settings; }

// --- cache file --------------------------------------------------------------------------------
// magic (its last byte the format version), key, settings, per level (band, far): origin xyz,
// voxel, scale, nbx nby nbz, bricks, exact_cells, brick_of, values, flags; checksum (FNV-1a of
// everything before it).

namespace {

template <class T>
void put(std::string& out, const T& v) {
  out.append(reinterpret_cast<const char*>(&v), sizeof(T));
}
template <class T>
void put_vec(std::string& out, const std::vector<T>& v) {
  out.append(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T));
}

struct Reader {
  const std::string& s;
  std::size_t at = 0;
  template <class T>
  bool get(T& v) {
    if (s.size() - at < sizeof(T)) return false;
    std::memcpy(&v, s.data() + at, sizeof(T));
    at += sizeof(T);
    return true;
  }
  template <class T>
  bool get_vec(std::vector<T>& v, std::size_t n) {
    if (n > (s.size() - at) / sizeof(T)) return false;
    v.resize(n);
    std::memcpy(v.data(), s.data() + at, n * sizeof(T));
    at += n * sizeof(T);
    return true;
  }
};

}  // namespace

Status SdfGrid::save(const std::filesystem::path& file, std::uint64_t key) const {
  const Data& d = *data_;
  std::string out;
  out.reserve(d.stats.memory_bytes + 512);
  out.append(kMagic.data(), kMagic.size());
  put(out, key);
  put(out, d.settings);
  for (const auto& L : d.levels) {
    put(out, L.origin.x()), put(out, L.origin.y()), put(out, L.origin.z());
    put(out, L.voxel), put(out, L.scale);
    put(out, L.nbx), put(out, L.nby), put(out, L.nbz);
    put(out, static_cast<std::uint64_t>(L.values.size() / kBrickValues));
    put(out, L.exact_cells);
    put_vec(out, L.brick_of);
    put_vec(out, L.values);
    put_vec(out, L.flags);
  }
  put(out, fnv1a(out.data(), out.size()));
  return write_file_atomic(file, out);
}

std::optional<SdfGrid> SdfGrid::load(const std::filesystem::path& file, std::uint64_t key, SignedDistance exact,
                                     std::string* why) {
  auto fail = [&](const std::string& what) -> std::optional<SdfGrid> {
    if (why != nullptr) *why = file.string() + ": " + what;
    return std::nullopt;
  };
  std::ifstream in(file, std::ios::binary);
  if (!in) return fail("no cache file");
  const std::string s((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (s.size() < kMagic.size() + 2 * sizeof(std::uint64_t) || std::memcmp(s.data(), kMagic.data(), kMagic.size() - 1) != 0)
    return fail("not a signed-distance grid cache (bad magic)");
  if (const char v = s[kMagic.size() - 1]; v != kMagic.back())
    return fail("written in format version " + (v >= '0' && v <= '9' ? std::string(1, v) : std::string("?")) +
                ", this build reads version " + kMagic.back());
  std::uint64_t stored_sum = 0;
  std::memcpy(&stored_sum, s.data() + s.size() - sizeof(stored_sum), sizeof(stored_sum));
  if (fnv1a(s.data(), s.size() - sizeof(stored_sum)) != stored_sum) return fail("corrupt (checksum mismatch)");
  Reader r{s, kMagic.size()};
  std::uint64_t stored_key = 0;
  auto d = std::make_shared<Data>();
  if (!r.get(stored_key)) return fail("truncated");
  if (stored_key != key) return fail("written for another golden template or other settings");
  if (!r.get(d->settings)) return fail("truncated");
  if (!(d->settings.kink_jump_mm >= 0 && std::isfinite(d->settings.kink_jump_mm))) return fail("invalid header");
  for (auto& L : d->levels) {
    double ox = 0, oy = 0, oz = 0;
    std::uint64_t bricks = 0;
    if (!r.get(ox) || !r.get(oy) || !r.get(oz) || !r.get(L.voxel) || !r.get(L.scale) || !r.get(L.nbx) ||
        !r.get(L.nby) || !r.get(L.nbz) || !r.get(bricks) || !r.get(L.exact_cells))
      return fail("truncated");
    if (!(L.voxel > 0) || !(L.scale > 0) || L.nbx <= 0 || L.nby <= 0 || L.nbz <= 0 ||
        L.nbx * L.nby * L.nbz > (std::int64_t{1} << 31) || bricks > (std::uint64_t{1} << 31))
      return fail("invalid header");
    const auto slots = static_cast<std::size_t>(L.nbx * L.nby * L.nbz);
    if (!r.get_vec(L.brick_of, slots) || !r.get_vec(L.values, bricks * kBrickValues) ||
        !r.get_vec(L.flags, bricks * kFlagWords))
      return fail("truncated");
    for (const auto b : L.brick_of)
      if (b < -1 || (b >= 0 && static_cast<std::uint64_t>(b) >= bricks)) return fail("bad brick index");
    L.origin = Vec3(ox, oy, oz);
    L.inv_voxel = 1.0 / L.voxel;
  }
  if (r.at + sizeof(stored_sum) != s.size()) return fail("trailing bytes");
  d->exact = std::move(exact);
  d->update_stats();
  SdfGrid g;
  g.data_ = std::move(d);
  return g;
}

std::uint64_t sdf_grid_key(const std::vector<Vec3>& points, const std::vector<Vec3>& normals, const std::string& parameters) {
  std::uint64_t h = fnv1a(kMagic.data(), kMagic.size());
  h = fnv1a(parameters.data(), parameters.size(), h);
  const std::uint64_t n = points.size();
  h = fnv1a(&n, sizeof(n), h);
  h = fnv1a(points.data(), points.size() * sizeof(Vec3), h);
  return fnv1a(normals.data(), normals.size() * sizeof(Vec3), h);
}

}  // namespace fettle::planning
