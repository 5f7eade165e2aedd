// Fuzz target: point-cloud files as `fettle locate` and template scans read them
// (vision/cloud.hpp load_cloud: PLY and PCD through Fettle's own readers). The first
// byte picks the extension. Any file gives finite points (and unit or zero normals) or a
// UserError; a header claiming billions of points must not make it allocate gigabytes
// (libFuzzer's -rss_limit_mb and -malloc_limit_mb catch that).
#include <cmath>
#include <cstdint>

#include "fettle/core/error.hpp"
#include "fettle/vision/cloud.hpp"
#include "fuzz_input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  const bool pcd = in.take<std::uint8_t>() % 2 == 0;
  const auto file = fettle::fuzz::write_scratch(pcd ? "cloud.pcd" : "cloud.ply", in.rest());
  try {
    const auto cloud = fettle::vision::load_cloud(file);
    FUZZ_CHECK(!cloud.empty());
    for (const auto& p : cloud.points) FUZZ_CHECK(p.allFinite());
    if (cloud.has_normals())
      for (const auto& n : cloud.normals) FUZZ_CHECK(n.isZero() || std::abs(n.norm() - 1.0f) < 1e-3f);
  } catch (const fettle::UserError&) {
    // A bad file is the user's to fix; the message names it.
  }
  return 0;
}
