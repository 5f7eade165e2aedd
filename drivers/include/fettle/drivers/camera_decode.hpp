#pragma once
// Decoding GigE Vision 3D frames (GenICam SFNC Scan3d) into organized clouds.
//
// Pure functions: no camera needed. The driver (camera.hpp) reads the Scan3d features
// from the camera into Scan3dParameters and hands every received frame to decode_frame().
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>

#include "fettle/core/cloud.hpp"
#include "fettle/core/result.hpp"

namespace fettle::drivers {

/// GenICam PFNC pixel format codes this driver knows by name.
namespace pfnc {
inline constexpr std::uint32_t Mono8 = 0x01080001u;
inline constexpr std::uint32_t Mono16 = 0x01100007u;
inline constexpr std::uint32_t Coord3D_C16 = 0x011000B8u;     ///< range map, 16-bit, scaled
inline constexpr std::uint32_t Coord3D_C32f = 0x012000BFu;    ///< range map, float
inline constexpr std::uint32_t Coord3D_ABC32f = 0x026000C0u;  ///< point cloud, 3 floats per pixel
}  // namespace pfnc

/// The PFNC name of a pixel format ("Mono8", "Coord3D_C16"), or "0x........" if unknown.
std::string pixel_format_name(std::uint32_t pixel_format);
/// The code of a PFNC name this driver knows; nullopt otherwise.
std::optional<std::uint32_t> pixel_format_from_name(const std::string& name);
/// True for the formats decode_frame() accepts.
bool is_supported_pixel_format(std::uint32_t pixel_format);

/// Pinhole intrinsics of the range map, pixels.
struct Intrinsics {
  double fx_px = 0.0;
  double fy_px = 0.0;
  double cx_px = 0.0;
  double cy_px = 0.0;
};

/// What the camera's Scan3d features say about its 3D data (SFNC names in comments).
struct Scan3dParameters {
  double scale = 1.0;                 ///< Scan3dCoordinateScale (CoordinateC), distance units per count
  double offset = 0.0;                ///< Scan3dCoordinateOffset (CoordinateC), distance units
  bool invalid_data_flag = false;     ///< Scan3dInvalidDataFlag
  double invalid_data_value = 0.0;    ///< Scan3dInvalidDataValue (raw value that marks "no data")
  double unit_mm = 1.0;               ///< Scan3dDistanceUnit: Millimeter 1, Inch 25.4
  std::optional<Intrinsics> intrinsics;  ///< Scan3dFocalLength, Scan3dPrincipalPointU/V (or a calibration)
};

/// One received frame: the payload as the camera sent it (little-endian pixels, row-major).
struct RawFrame {
  std::uint32_t pixel_format = 0;
  std::uint32_t width = 0;
  std::uint32_t height = 0;
  const std::byte* data = nullptr;
  std::size_t size = 0;
};

/// Decodes a frame into an organized cloud in millimetres, camera frame (invalid pixels NaN):
///  - Coord3D_C16 / Coord3D_C32f: range maps, z = raw * scale + offset (C16) or raw (C32f),
///    x = (u - cx) z / fx, y = (v - cy) z / fy; raw == invalid_data_value (flag set) → NaN;
///  - Coord3D_ABC32f: x, y, z per pixel; NaN or C == invalid_data_value → NaN.
/// Errors: "camera.unsupported_pixel_format" naming the format, "camera.bad_frame" (size),
/// "camera.no_intrinsics" (range map without intrinsics). `out` is reused to avoid reallocation.
Status decode_frame(const RawFrame& frame, const Scan3dParameters& parameters, OrganizedCloud& out);
Result<OrganizedCloud> decode_frame(const RawFrame& frame, const Scan3dParameters& parameters);

}  // namespace fettle::drivers
