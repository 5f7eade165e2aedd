// The simulated camera's range images from the simulator's scanner (sim.hpp): the casting in
// the fixture, seen from the camera on the slide.
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>

#include "fettle/sim/camera.hpp"
#include "fettle/sim/sim.hpp"

namespace fettle::sim {

RangeImageSource scanner_range_source(const config::PartRecipe& recipe, std::uint64_t seed,
                                      const RangeImageModel& requested, bool noise, const config::CellConfig* cell) {
  ScannerConfig config;
  if (cell != nullptr) config.place_in_cell(*cell);
  config.intrinsics = config.intrinsics.scaled(static_cast<int>(requested.width), static_cast<int>(requested.height));
  // A 3D camera delivers rectified range maps (SFNC RectifiedC): no lens distortion left.
  config.intrinsics.k1 = config.intrinsics.k2 = config.intrinsics.p1 = config.intrinsics.p2 = config.intrinsics.k3 = 0.0;
  config.intrinsics.fy = config.intrinsics.fx;  // Scan3dFocalLength is one value
  config.noise.enabled = noise;

  RangeImageModel model = requested;
  model.focal_px = config.intrinsics.fx;
  model.cx_px = config.intrinsics.cx;
  model.cy_px = config.intrinsics.cy;

  auto casting = std::make_shared<const Casting>(Casting::make(recipe, seed));
  auto scanner = std::make_shared<const Scanner>(config);
  RangeImageSource source;
  source.model = model;
  source.description = "casting " + std::to_string(seed) + " of " + casting->part_id() + " (simulator scanner" +
                       (noise ? ", with noise" : ", ideal");
  if (cell != nullptr) {
    const Vec3 p = config.T_base_camera(0.0).translation();
    char at[120];
    std::snprintf(at, sizeof at, "; placed by %s: at slide 0 mm the camera is at base (%.1f, %.1f, %.1f) mm",
                  cell->source.string().c_str(), p.x(), p.y(), p.z());
    source.description += at;
  }
  source.description += ")";
  source.render = [casting, scanner, model](double slide_mm, std::vector<std::uint16_t>& out) {
    const Capture capture = scanner->capture(*casting, slide_mm);
    const auto& z = capture.range;
    out.assign(std::size_t{model.width} * model.height, model.invalid);
    if (z.width != model.width || z.height != model.height) return;
    for (std::size_t i = 0; i < out.size(); ++i) {
      const float v = z.data[i];
      if (!std::isfinite(v)) continue;
      const double raw = std::round((v - model.offset_mm) / model.scale_mm);
      if (raw >= 1.0 && raw <= 65535.0 && raw != model.invalid) out[i] = static_cast<std::uint16_t>(raw);
    }
  };
  return source;
}

}  // namespace fettle::sim
