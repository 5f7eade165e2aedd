// Fuzz target: the PLY reader (fettle/core/ply.hpp), which reads back the scans and clouds
// Fettle saved. Any file gives a cloud whose grid matches its points or ply.bad; a header that lies about the vertex count (or claims billions)
// must not make it allocate more than the file can hold.
#include <cstdint>

#include "fettle/core/ply.hpp"
#include "fuzz_input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  const auto file = fettle::fuzz::write_scratch("scan.ply", in.rest());
  auto cloud = fettle::read_ply(file);
  if (cloud) {
    FUZZ_CHECK(std::size_t{cloud->width} * cloud->height == cloud->points.size());
    FUZZ_CHECK(cloud->points.size() * 12 <= size);
  } else {
    FUZZ_CHECK(cloud.error().code == "ply.bad");
  }
  return 0;
}
