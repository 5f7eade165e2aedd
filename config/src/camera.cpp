// 3D camera (GigE Vision) and its slide: [camera] and [slide] in the cell file.
#include "fettle/config/camera.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_camera(TableReader& root, SlideSection& slide, CameraSection& c) {
  if (auto t = root.table("slide", Need::required)) {
    t->numbers("photo_positions_mm", slide.photo_positions_mm, {-10000.0, 10000.0}, 1, 16, Need::required);
    t->number("home_mm", slide.home_mm, {-10000.0, 10000.0});
    t->integer("travel_timeout_ms", slide.travel_timeout_ms, kTimeoutMs);
  }
  if (auto t = root.table("camera", Need::required)) {
    const bool by_address = t->has("address");
    const bool by_serial = t->has("serial");
    t->ipv4("address", c.address);
    t->ident("serial", c.serial, 64);
    if (!by_address && !by_serial) t->error("address", "set the camera's address (IPv4) or its serial number");
    if (by_address && by_serial) t->error("serial", "set either address or serial, not both");
    t->integer("frame_timeout_ms", c.frame_timeout_ms, kTimeoutMs);
    t->integer("retries", c.retries, {0, 100});
    t->number("exposure_us", c.exposure_us, {1.0, 10e6});
    t->choice("pixel_format", c.pixel_format, {"Coord3D_C16", "Coord3D_C32f", "Coord3D_ABC32f"});
    t->integer("packet_size_bytes", c.packet_size_bytes, {0, 65000});
    t->choice("intrinsics", c.intrinsics, {"camera", "calibration"});
  }
}

}  // namespace fettle::config::detail
