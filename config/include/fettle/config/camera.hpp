#pragma once
// 3D camera (GigE Vision) and its slide: [camera] and [slide] in the cell file.
#include <array>
#include <filesystem>
#include <string>
#include <vector>

namespace fettle::config {

struct SlideSection {
  std::vector<double> photo_positions_mm{0.0};  ///< slide positions where the camera takes a view
  /// Where the PLC parks the slide (slide_position 0), out of the robot's way; no view is taken
  /// there. Fettle only commands it; the simulated PLC drives the slide there.
  double home_mm = -100.0;
  int travel_timeout_ms = 15000;
};

struct CameraSection {
  std::string address;  ///< IPv4 of the GigE Vision camera (or use serial)
  std::string serial;   ///< serial number (or use address)
  int frame_timeout_ms = 5000;
  int retries = 2;
  double exposure_us = 20000.0;
  std::string pixel_format;        ///< Coord3D_C16 | Coord3D_C32f | Coord3D_ABC32f; empty = the camera's own
  int packet_size_bytes = 0;       ///< GevSCPSPacketSize; 0 = the camera's own
  std::string intrinsics = "camera";  ///< range-map intrinsics: "camera" (Scan3d features) or "calibration"
};

}  // namespace fettle::config
