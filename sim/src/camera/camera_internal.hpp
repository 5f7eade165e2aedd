#pragma once
// Private to the simulated camera.
namespace fettle::sim::detail {
extern const char* const kCameraGenicamXml;
}  // namespace fettle::sim::detail
