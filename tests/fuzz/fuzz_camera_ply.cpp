// Fuzz target: the organized-cloud PLY reader of the camera driver (drivers/camera_ply.hpp),
// which reads back the scans Fettle saved. Any file gives a cloud whose grid matches its
// points or camera.bad_ply; a header that lies about the vertex count (or claims billions)
// must not make it allocate more than the file can hold.
#include <cstdint>

#include "fettle/drivers/camera_ply.hpp"
#include "fuzz_input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  const auto file = fettle::fuzz::write_scratch("scan.ply", in.rest());
  auto cloud = fettle::drivers::read_ply(file);
  if (cloud) {
    FUZZ_CHECK(std::size_t{cloud->width} * cloud->height == cloud->points.size());
    FUZZ_CHECK(cloud->points.size() * 12 <= size);
  } else {
    FUZZ_CHECK(cloud.error().code == "camera.bad_ply");
  }
  return 0;
}
