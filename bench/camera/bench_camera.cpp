// bench_camera: Scan3d decoding of one 3.2 MP (2064 x 1544) frame, per pixel format, and a
// full capture from the simulated GigE Vision camera over loopback.
//   build/bin/bench_camera            (the decode target is <= 100 ms per frame)
#include <benchmark/benchmark.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "fettle/drivers/camera.hpp"
#include "fettle/drivers/camera_decode.hpp"
#include "fettle/sim/camera.hpp"

namespace fd = fettle::drivers;

namespace {

constexpr std::uint32_t kW = 2064, kH = 1544;

fd::Scan3dParameters params() {
  fd::Scan3dParameters p;
  p.scale = 0.02;
  p.invalid_data_flag = true;
  p.invalid_data_value = 0;
  p.intrinsics = fd::Intrinsics{2400.0, 2400.0, 1031.5, 771.5};
  return p;
}

/// A plane-and-sphere range map (the simulator's synthetic scene) with some invalid pixels.
std::vector<std::uint16_t> range_map() {
  fettle::sim::RangeImageModel m;
  std::vector<std::uint16_t> r;
  fettle::sim::synthetic_range_source(m, {}).render(0.0, r);
  for (std::size_t i = 0; i < r.size(); i += 97) r[i] = 0;
  return r;
}

void BM_DecodeC16(benchmark::State& state) {
  const auto raw = range_map();
  const fd::RawFrame f{fd::pfnc::Coord3D_C16, kW, kH, reinterpret_cast<const std::byte*>(raw.data()), raw.size() * 2};
  fettle::OrganizedCloud cloud;
  const auto p = params();
  for (auto _ : state) {
    auto s = fd::decode_frame(f, p, cloud);
    benchmark::DoNotOptimize(cloud.points.data());
    if (!s) state.SkipWithError(s.error().message.c_str());
  }
  state.counters["MP"] = kW * kH / 1e6;
}

void BM_DecodeC16FreshCloud(benchmark::State& state) {
  const auto raw = range_map();
  const fd::RawFrame f{fd::pfnc::Coord3D_C16, kW, kH, reinterpret_cast<const std::byte*>(raw.data()), raw.size() * 2};
  const auto p = params();
  for (auto _ : state) {
    auto cloud = fd::decode_frame(f, p);  // allocates the 3.2 M points every time
    benchmark::DoNotOptimize(cloud);
  }
}

void BM_DecodeC32f(benchmark::State& state) {
  const auto raw16 = range_map();
  std::vector<float> raw(raw16.size());
  for (std::size_t i = 0; i < raw.size(); ++i) raw[i] = raw16[i] == 0 ? NAN : raw16[i] * 0.02f;
  const fd::RawFrame f{fd::pfnc::Coord3D_C32f, kW, kH, reinterpret_cast<const std::byte*>(raw.data()), raw.size() * 4};
  fettle::OrganizedCloud cloud;
  const auto p = params();
  for (auto _ : state) {
    auto s = fd::decode_frame(f, p, cloud);
    benchmark::DoNotOptimize(cloud.points.data());
    if (!s) state.SkipWithError(s.error().message.c_str());
  }
}

void BM_DecodeABC32f(benchmark::State& state) {
  std::vector<float> raw(std::size_t{kW} * kH * 3, 1.0f);
  const fd::RawFrame f{fd::pfnc::Coord3D_ABC32f, kW, kH, reinterpret_cast<const std::byte*>(raw.data()),
                       raw.size() * 4};
  fettle::OrganizedCloud cloud;
  const auto p = params();
  for (auto _ : state) {
    auto s = fd::decode_frame(f, p, cloud);
    benchmark::DoNotOptimize(cloud.points.data());
    if (!s) state.SkipWithError(s.error().message.c_str());
  }
}

/// Trigger to decoded cloud, 3.2 MP Coord3D_C16 over loopback (GVSP through Aravis).
/// Arg 1: capture(CameraCapture&) reusing the cloud (the cycle path); 0: capture() returning a
/// fresh 3.2 MP cloud every time. decode_ms is the target (<= 100 ms after the frame
/// arrived); transfer_ms is trigger to complete frame through the in-process fake camera.
void BM_CaptureFromSimulatedCamera(benchmark::State& state) {
  try {
    fettle::sim::SimulatedCamera sim({}, fettle::sim::synthetic_range_source({}, {}));
    fd::CameraOptions o;
    o.address = "127.0.0.1";
    o.frame_timeout_ms = 5000;
    fd::Camera camera(o);
    const bool reuse = state.range(0) != 0;
    double decode_ms = 0.0, wait_ms = 0.0;
    std::uint64_t missing = 0, attempts = 0;
    fd::CameraCapture reused;
    for (auto _ : state) {
      fd::CameraCapture fresh;
      fd::CameraCapture& c = reuse ? reused : fresh;
      if (reuse) {
        if (auto s = camera.capture(c); !s) {
          state.SkipWithError(s.error().message.c_str());
          break;
        }
      } else {
        auto r = camera.capture();
        if (!r) {
          state.SkipWithError(r.error().message.c_str());
          break;
        }
        c = std::move(*r);
      }
      decode_ms += c.stats.decode_ms;
      wait_ms += c.stats.wait_ms;
      missing += c.stats.missing_packets;
      attempts += static_cast<std::uint64_t>(c.stats.attempts);
    }
    const double n = static_cast<double>(state.iterations());
    state.counters["decode_ms"] = decode_ms / n;
    state.counters["transfer_ms"] = wait_ms / n;
    state.counters["missing_packets"] = static_cast<double>(missing);
    state.counters["attempts"] = static_cast<double>(attempts) / n;
  } catch (const std::exception& e) {
    state.SkipWithError(e.what());
  }
}

}  // namespace

BENCHMARK(BM_DecodeC16)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_DecodeC16FreshCloud)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_DecodeC32f)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_DecodeABC32f)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_CaptureFromSimulatedCamera)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond)->Iterations(5)->UseRealTime();

BENCHMARK_MAIN();
