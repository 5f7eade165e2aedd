#pragma once
// A precomputed signed-distance grid over the template: the exact (sample-based) signed
// distance evaluated once per recipe on a lattice in a band around the surface, answered per
// query by trilinear interpolation. The planner asks the signed distance millions of times per
// part (tool probes, back-offs, level searches, validation); the exact nearest-sample search
// cost seconds, a grid lookup costs tens of nanoseconds.
//
// Semantics are the exact function's (sign, convex / concave edges): every lattice value is an
// exact answer, and a lattice cell whose interpolated centre differs from the exact answer
// there by more than the tolerance (a kink: an edge, a concave corner's bisector) is answered
// by the exact function, as is every point no lattice covers.
//
// Two lattices: the band (fine, `voxel_mm`, where the surface may be within `band_mm`) and the
// far field (coarse, `far_voxel_mm`, out to `far_band_mm`: tool probes in the air, level
// searches high above a face). The first lattice covering a point answers it. Each is made of
// bricks of 8×8×8 cells (9³ lattice values each, int16, so every cell's eight corners are in
// one brick), allocated only where the brick may lie within its band of the surface, with a
// dense table of brick indices over the box.
// See docs/planning.md.
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "fettle/core/geometry.hpp"
#include "fettle/planning/planner.hpp"

namespace fettle::planning {

struct SdfGridSettings {
  double voxel_mm = 0.5;       ///< band lattice spacing
  double band_mm = 3.0;        ///< band lattice where the surface may be this near
  double exact_tol_mm = 0.03;  ///< band cells interpolated worse than this at their centre: exact
  double far_voxel_mm = 2.0;   ///< far lattice spacing (beyond the band: tool probes in the air,
  double far_band_mm = 25.0;   ///< level searches), out to this distance from the surface
  double far_tol_mm = 0.1;     ///< far cells interpolated worse than this at their centre: exact
  /// How far the exact function may jump within a cell (about a sample spacing off the sampled
  /// patch): with half a cell's diagonal, the bound SignedDistance::near trusts a kink cell's
  /// interpolated value within. Not a bound beside an open border of the samples (the sign
  /// flips across the border's plane there): a golden seen from above is open at the table.
  double kink_jump_mm = 1.0;
  int threads = 0;             ///< build threads (0: the hardware's)
};

/// Build statistics (also after a load from the cache).
struct SdfGridStats {
  std::size_t bricks = 0;         ///< allocated bricks of 8³ cells
  std::size_t brick_slots = 0;    ///< bricks of the whole box
  std::size_t exact_cells = 0;    ///< band cells answered by the exact function (kinks)
  std::size_t far_bricks = 0;     ///< allocated bricks of the far lattice
  std::size_t far_exact_cells = 0;
  std::size_t memory_bytes = 0;   ///< lattice values + flags + brick table
  double build_ms = 0.0;          ///< 0 when loaded
};

class SdfGrid {
 public:
  /// (lattice "band" or "far", bricks done, bricks total) during a build, from the calling thread.
  using Progress = std::function<void(const char* lattice, std::size_t done, std::size_t total)>;

  /// Evaluates `exact` over the box [box_min, box_max] grown by the band (in parallel).
  /// `exact` must be safe to call concurrently; it is kept for the cells and points the
  /// lattice does not answer.
  static SdfGrid build(SignedDistance exact, const Vec3& box_min, const Vec3& box_max, const SdfGridSettings& settings,
                       const Progress& progress = {});

  /// The cached grid in `file` when it was written for `key`; nullopt (and `why` says what
  /// was wrong: missing, another key, truncated, checksum) otherwise. `exact` as for build().
  static std::optional<SdfGrid> load(const std::filesystem::path& file, std::uint64_t key, SignedDistance exact,
                                     std::string* why = nullptr);
  /// Writes the grid with its key (atomically: a reader sees the old file or the new one).
  Status save(const std::filesystem::path& file, std::uint64_t key) const;

  /// Interpolated signed distance (mm, > 0 outside), or the exact one where the lattice
  /// does not answer.
  [[nodiscard]] double operator()(const Vec3& p) const;
  /// The lattice's answer only: nullopt where the exact function would be asked (tests).
  [[nodiscard]] std::optional<double> interpolated(const Vec3& p) const;
  /// A SignedDistance sharing this grid (cheap to copy, safe to call concurrently); its near()
  /// answers a kink cell from the lattice when the value is beyond near_mm by more than half
  /// the cell's diagonal plus kink_jump_mm.
  [[nodiscard]] SignedDistance function() const;

  [[nodiscard]] const SdfGridStats& stats() const;
  [[nodiscard]] const SdfGridSettings& settings() const;

 private:
  struct Data;
  std::shared_ptr<const Data> data_;
};

/// FNV-1a 64-bit hash of the samples and of everything else a cached grid depends on: the key
/// of the on-disk cache (a changed golden or setting gives another key).
std::uint64_t sdf_grid_key(const std::vector<Vec3>& points, const std::vector<Vec3>& normals,
                           const std::string& parameters);

}  // namespace fettle::planning
