// Decoding GenICam SFNC Scan3d frames into organized clouds (see camera_decode.hpp).
#include <array>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <utility>
#include <vector>

#include "fettle/drivers/camera_decode.hpp"

namespace fettle::drivers {
namespace {

struct NamedFormat {
  std::uint32_t code;
  const char* name;
};

// PFNC codes (GenICam Pixel Format Naming Convention) for the names people will meet.
constexpr std::array<NamedFormat, 22> kFormats{{
    {pfnc::Mono8, "Mono8"},
    {0x01100003u, "Mono10"},
    {0x01100005u, "Mono12"},
    {pfnc::Mono16, "Mono16"},
    {0x01080008u, "BayerGR8"},
    {0x01080009u, "BayerRG8"},
    {0x0108000Au, "BayerGB8"},
    {0x0108000Bu, "BayerBG8"},
    {0x02180014u, "RGB8"},
    {0x02180015u, "BGR8"},
    {0x02100032u, "YUV422_8"},
    {0x011000B6u, "Coord3D_A16"},
    {0x011000B7u, "Coord3D_B16"},
    {pfnc::Coord3D_C16, "Coord3D_C16"},
    {0x012000BDu, "Coord3D_A32f"},
    {0x012000BEu, "Coord3D_B32f"},
    {pfnc::Coord3D_C32f, "Coord3D_C32f"},
    {0x023000B9u, "Coord3D_ABC16"},
    {pfnc::Coord3D_ABC32f, "Coord3D_ABC32f"},
    {0x026000C1u, "Coord3D_ABC32f_Planar"},
    {0x010800B1u, "Coord3D_C8"},
    {0x011000B9u, "Confidence16"},
}};

std::size_t bytes_per_pixel(std::uint32_t pixel_format) { return ((pixel_format >> 16) & 0xFFu) / 8u; }

template <class T>
T load_le(const std::byte* p) {
  T v;
  std::memcpy(&v, p, sizeof(T));  // x86/ARM little-endian hosts, as GVSP payloads
  return v;
}

Error error(std::string code, std::string message) { return Error{std::move(code), std::move(message)}; }

}  // namespace

std::string pixel_format_name(std::uint32_t pixel_format) {
  for (const auto& f : kFormats)
    if (f.code == pixel_format) return f.name;
  char buf[16];
  std::snprintf(buf, sizeof buf, "0x%08X", pixel_format);
  return buf;
}

std::optional<std::uint32_t> pixel_format_from_name(const std::string& name) {
  for (const auto& f : kFormats)
    if (name == f.name) return f.code;
  return std::nullopt;
}

bool is_supported_pixel_format(std::uint32_t pixel_format) {
  return pixel_format == pfnc::Coord3D_C16 || pixel_format == pfnc::Coord3D_C32f ||
         pixel_format == pfnc::Coord3D_ABC32f;
}

Status decode_frame(const RawFrame& frame, const Scan3dParameters& p, OrganizedCloud& out) {
  const std::string format = pixel_format_name(frame.pixel_format);
  if (!is_supported_pixel_format(frame.pixel_format))
    return error("camera.unsupported_pixel_format",
                 "unsupported pixel format " + format +
                     ": the camera must send 3D data as Coord3D_C16, Coord3D_C32f or Coord3D_ABC32f "
                     "(set [camera] pixel_format or the camera's PixelFormat)");
  const std::size_t n = std::size_t{frame.width} * frame.height;  // < 2^64: two 32-bit factors
  const std::size_t bpp = bytes_per_pixel(frame.pixel_format);
  // A leader with absurd sizes must not overflow the byte count (and then pass the size check).
  const bool overflow = n > std::numeric_limits<std::size_t>::max() / bpp;
  const std::size_t needed = overflow ? std::numeric_limits<std::size_t>::max() : n * bpp;
  if (frame.width == 0 || frame.height == 0 || frame.data == nullptr || frame.size < needed)
    return error("camera.bad_frame", "frame of " + std::to_string(frame.size) + " bytes is too small for " +
                                         std::to_string(frame.width) + "x" + std::to_string(frame.height) +
                                         " " + format + " (" + std::to_string(needed) + " bytes)");
  out.width = frame.width;
  out.height = frame.height;
  out.points.resize(n);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const Eigen::Vector3f invalid{nan, nan, nan};
  const double unit = p.unit_mm;

  if (frame.pixel_format == pfnc::Coord3D_ABC32f) {
    const auto inv = static_cast<float>(p.invalid_data_value);
    for (std::size_t i = 0; i < n; ++i) {
      const std::byte* px = frame.data + i * 12;
      const float a = load_le<float>(px), b = load_le<float>(px + 4), c = load_le<float>(px + 8);
      const bool bad = !std::isfinite(a) || !std::isfinite(b) || !std::isfinite(c) ||
                       (p.invalid_data_flag && c == inv);
      out.points[i] = bad ? invalid
                          : Eigen::Vector3f(static_cast<float>(a * unit), static_cast<float>(b * unit),
                                            static_cast<float>(c * unit));
    }
    return {};
  }

  if (!p.intrinsics || p.intrinsics->fx_px <= 0.0 || p.intrinsics->fy_px <= 0.0)
    return error("camera.no_intrinsics",
                 format + " is a range map and needs intrinsics: the camera has no Scan3dFocalLength / "
                          "Scan3dPrincipalPointU/V, so set [camera] intrinsics = \"calibration\" with a "
                          "calibration file that has them");
  const Intrinsics& k = *p.intrinsics;
  // Per-column and per-row ray slopes: x = kx[u] * z, y = ky[v] * z.
  thread_local std::vector<float> kx, ky;
  kx.resize(frame.width);
  ky.resize(frame.height);
  for (std::uint32_t u = 0; u < frame.width; ++u) kx[u] = static_cast<float>((u - k.cx_px) / k.fx_px);
  for (std::uint32_t v = 0; v < frame.height; ++v) ky[v] = static_cast<float>((v - k.cy_px) / k.fy_px);

  if (frame.pixel_format == pfnc::Coord3D_C16) {
    const auto scale = static_cast<float>(p.scale * unit), offset = static_cast<float>(p.offset * unit);
    const bool check = p.invalid_data_flag;
    const double invd = p.invalid_data_value;
    const bool inv_representable = invd >= 0.0 && invd <= 65535.0 && std::floor(invd) == invd;
    const auto inv = static_cast<std::uint16_t>(inv_representable ? invd : 0.0);
    for (std::uint32_t v = 0; v < frame.height; ++v) {
      const std::byte* row = frame.data + std::size_t{v} * frame.width * 2;
      Eigen::Vector3f* dst = out.points.data() + std::size_t{v} * frame.width;
      const float yv = ky[v];
      for (std::uint32_t u = 0; u < frame.width; ++u) {
        const auto raw = load_le<std::uint16_t>(row + std::size_t{u} * 2);
        if (check && inv_representable && raw == inv) {
          dst[u] = invalid;
          continue;
        }
        const float z = static_cast<float>(raw) * scale + offset;
        dst[u] = Eigen::Vector3f(kx[u] * z, yv * z, z);
      }
    }
    return {};
  }

  // Coord3D_C32f
  const auto inv = static_cast<float>(p.invalid_data_value);
  for (std::uint32_t v = 0; v < frame.height; ++v) {
    const std::byte* row = frame.data + std::size_t{v} * frame.width * 4;
    Eigen::Vector3f* dst = out.points.data() + std::size_t{v} * frame.width;
    const float yv = ky[v];
    for (std::uint32_t u = 0; u < frame.width; ++u) {
      const float raw = load_le<float>(row + std::size_t{u} * 4);
      if (!std::isfinite(raw) || (p.invalid_data_flag && raw == inv)) {
        dst[u] = invalid;
        continue;
      }
      const auto z = static_cast<float>(raw * unit);
      dst[u] = Eigen::Vector3f(kx[u] * z, yv * z, z);
    }
  }
  return {};
}

Result<OrganizedCloud> decode_frame(const RawFrame& frame, const Scan3dParameters& parameters) {
  OrganizedCloud cloud;
  auto status = decode_frame(frame, parameters, cloud);
  if (!status) return status.error();
  return cloud;
}

}  // namespace fettle::drivers
