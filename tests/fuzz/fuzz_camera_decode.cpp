// Fuzz target: the Scan3d range-image decoder (drivers/camera_decode.hpp). The bytes give the
// frame's pixel format, width and height (as a camera's GVSP leader would), the Scan3d
// parameters, and the payload. Any frame decodes to a cloud of exactly width x height points
// or is refused with camera.bad_frame / camera.unsupported_pixel_format / camera.no_intrinsics;
// it never reads past the payload or allocates more than the payload can fill.
#include <cstdint>
#include <cstring>
#include <vector>

#include "fettle/drivers/camera_decode.hpp"
#include "fuzz_input.hpp"

namespace drivers = fettle::drivers;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  static constexpr std::uint32_t kFormats[] = {drivers::pfnc::Coord3D_C16, drivers::pfnc::Coord3D_C32f,
                                               drivers::pfnc::Coord3D_ABC32f, drivers::pfnc::Mono16};
  const auto selector = in.take<std::uint8_t>();
  drivers::RawFrame frame;
  frame.pixel_format = selector < 252 ? kFormats[selector % 4] : in.take<std::uint32_t>();
  // Small sizes usually (so frames with data are common), any 32-bit size sometimes.
  const bool wide = in.take_bool();
  frame.width = wide ? in.take<std::uint32_t>() : in.take<std::uint8_t>();
  frame.height = wide ? in.take<std::uint32_t>() : in.take<std::uint8_t>();

  drivers::Scan3dParameters p;
  p.scale = in.take<double>();
  p.offset = in.take<double>();
  p.invalid_data_flag = in.take_bool();
  p.invalid_data_value = in.take<double>();
  p.unit_mm = in.take_bool() ? 25.4 : 1.0;
  if (in.take_bool()) p.intrinsics = drivers::Intrinsics{in.take<double>(), in.take<double>(), in.take<double>(), in.take<double>()};

  const auto payload = in.rest();
  // A copy, so that ASan sees the payload's exact extent.
  std::vector<std::byte> bytes(payload.size());
  if (!payload.empty()) std::memcpy(bytes.data(), payload.data(), payload.size());
  frame.data = bytes.empty() ? nullptr : bytes.data();
  frame.size = bytes.size();

  auto cloud = drivers::decode_frame(frame, p);
  if (cloud) {
    FUZZ_CHECK(cloud->width == frame.width && cloud->height == frame.height);
    FUZZ_CHECK(cloud->points.size() == std::size_t{frame.width} * frame.height);
    FUZZ_CHECK(cloud->points.size() <= frame.size);
    (void)cloud->count_valid();
  } else {
    const auto& code = cloud.error().code;
    FUZZ_CHECK(code == "camera.bad_frame" || code == "camera.unsupported_pixel_format" ||
               code == "camera.no_intrinsics");
  }
  (void)drivers::pixel_format_name(frame.pixel_format);
  return 0;
}
