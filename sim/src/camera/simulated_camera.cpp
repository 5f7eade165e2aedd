// The simulated GigE Vision 3D camera (see camera.hpp).
#include "fettle/sim/camera.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <arv.h>

#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <mutex>
#include <thread>

#include "camera_internal.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"

namespace fettle::sim {
namespace {

auto logger() { return log::get("sim.camera"); }

// GigE Vision bootstrap register SCPS0 (stream channel 0 packet size).
constexpr guint32 kGevScps0 = 0x0D04;
// Our Scan3d block (see genicam_xml.cpp).
constexpr guint32 kScale = 0xA000, kOffset = 0xA008, kInvalidFlag = 0xA010, kInvalidValue = 0xA018,
                  kAxisMin = 0xA020, kAxisMax = 0xA028, kFocal = 0xA030, kPpu = 0xA038, kPpv = 0xA040;
constexpr std::uint32_t kCoord3D_C16 = 0x011000B8u, kCoord3D_C32f = 0x012000BFu, kCoord3D_ABC32f = 0x026000C0u,
                        kMono8 = 0x01080001u;

void write_double_be(ArvFakeCamera* cam, guint32 address, double value) {
  auto bits = std::bit_cast<std::uint64_t>(value);
  unsigned char be[8];
  for (int i = 7; i >= 0; --i) {
    be[i] = static_cast<unsigned char>(bits & 0xFFu);
    bits >>= 8;
  }
  arv_fake_camera_write_memory(cam, address, 8, be);
}

std::atomic<int> xml_files{0};

/// True if UDP `address`:3956 is free (ArvGvFakeCamera does not report a failed bind).
bool gvcp_port_free(const std::string& address) {
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(3956);
  if (::inet_pton(AF_INET, address.c_str(), &a.sin_addr) != 1)
    throw UserError("simulated camera: address '" + address + "' is not an IPv4 address");
  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  const bool free = fd >= 0 && ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
  if (fd >= 0) ::close(fd);
  return free;
}

}  // namespace

double synthetic_depth_mm(const RangeImageModel& m, const SyntheticScene& s, double slide_mm, double u, double v) {
  const double dx = (u - m.cx_px) / m.focal_px, dy = (v - m.cy_px) / m.focal_px;
  double best = std::numeric_limits<double>::quiet_NaN();
  if (s.plane_z_mm > 0.0) best = s.plane_z_mm;
  const double cx = s.sphere_center_mm[0] - slide_mm, cy = s.sphere_center_mm[1], cz = s.sphere_center_mm[2];
  const double dd = dx * dx + dy * dy + 1.0;
  const double dc = dx * cx + dy * cy + cz;
  const double disc = dc * dc - dd * (cx * cx + cy * cy + cz * cz - s.sphere_radius_mm * s.sphere_radius_mm);
  if (disc >= 0.0) {
    const double t = (dc - std::sqrt(disc)) / dd;  // z of the nearer hit (ray z component is 1)
    if (t > 0.0 && (std::isnan(best) || t < best)) best = t;
  }
  return best;
}

RangeImageSource synthetic_range_source(const RangeImageModel& model, const SyntheticScene& scene) {
  RangeImageSource src;
  src.model = model;
  src.description = "synthetic plane and sphere";
  src.render = [model, scene](double slide_mm, std::vector<std::uint16_t>& out) {
    out.resize(std::size_t{model.width} * model.height);
    for (std::uint32_t v = 0; v < model.height; ++v)
      for (std::uint32_t u = 0; u < model.width; ++u) {
        const double z = synthetic_depth_mm(model, scene, slide_mm, u, v);
        const double raw = std::round((z - model.offset_mm) / model.scale_mm);
        out[std::size_t{v} * model.width + u] =
            std::isnan(z) || raw < 1.0 || raw > 65535.0 || raw == model.invalid ? model.invalid
                                                                                 : static_cast<std::uint16_t>(raw);
      }
  };
  return src;
}

struct SimulatedCamera::Impl {
  SimulatedCameraOptions options;
  RangeImageSource source;
  std::filesystem::path xml_file;
  ArvGvFakeCamera* gv = nullptr;
  ArvFakeCamera* fake = nullptr;  // owned by gv

  std::atomic<double> slide_mm{0.0};
  std::atomic<int> drop{0};
  std::atomic<int> loss_frames{0};
  std::atomic<double> loss_ratio{0.0};
  std::atomic<double> base_loss{0.0};
  std::atomic<int> stall_ms{0};
  std::atomic<std::uint64_t> sent{0};

  // The range image for the current slide position, rendered by whoever moves the slide
  // (never in the camera thread, which must keep answering the control channel).
  std::mutex render_mutex;  // one render at a time
  std::mutex image_mutex;   // guards `image`
  std::shared_ptr<const std::vector<std::uint16_t>> image;

  void render(double slide) {
    std::lock_guard render_lock(render_mutex);
    const auto t0 = std::chrono::steady_clock::now();
    auto next = std::make_shared<std::vector<std::uint16_t>>();
    source.render(slide, *next);
    const auto& m = source.model;
    if (next->size() != std::size_t{m.width} * m.height)
      throw DeviceError("simulated camera: the renderer returned " + std::to_string(next->size()) + " pixels, not " +
                        std::to_string(m.width) + "x" + std::to_string(m.height));
    {
      std::lock_guard lock(image_mutex);
      image = std::move(next);
      slide_mm = slide;
    }
    logger()->info("simulated camera: range image for slide {} mm rendered in {:.0f} ms", slide,
                   std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }

  Impl(SimulatedCameraOptions o, RangeImageSource s) : options(std::move(o)), source(std::move(s)) {
    if (!source.render) throw UserError("simulated camera: no range image renderer given");
    base_loss = options.packet_loss;
    if (!gvcp_port_free(options.address))
      throw DeviceError("simulated camera: UDP " + options.address +
                        ":3956 (GigE Vision control) is in use: another camera already runs on this address");
    xml_file = std::filesystem::temp_directory_path() /
               ("fettle-sim-camera-" + std::to_string(::getpid()) + "-" + std::to_string(xml_files++) + ".xml");
    {
      std::ofstream f(xml_file);
      f << detail::kCameraGenicamXml;
      if (!f) throw DeviceError("simulated camera: cannot write its GenICam file " + xml_file.string());
    }
    g_random_set_seed(static_cast<guint32>(options.seed));
    gv = arv_gv_fake_camera_new_full(options.address.c_str(), options.serial.c_str(), xml_file.c_str());
    if (gv == nullptr || arv_gv_fake_camera_is_running(gv) == FALSE) {
      cleanup();
      throw DeviceError("simulated camera: cannot listen on " + options.address +
                        " UDP 3956 (GigE Vision control): is another camera running on this address?");
    }
    fake = arv_gv_fake_camera_get_fake_camera(gv);
    const auto& m = source.model;
    arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_SENSOR_WIDTH, m.width);
    arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_SENSOR_HEIGHT, m.height);
    arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_WIDTH, m.width);
    arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_HEIGHT, m.height);
    arv_fake_camera_write_register(fake, ARV_FAKE_CAMERA_REGISTER_PIXEL_FORMAT, kCoord3D_C16);
    arv_fake_camera_write_register(fake, kGevScps0, options.packet_size_bytes);
    write_double_be(fake, kScale, m.scale_mm);
    write_double_be(fake, kOffset, m.offset_mm);
    arv_fake_camera_write_register(fake, kInvalidFlag, 1);
    write_double_be(fake, kInvalidValue, m.invalid);
    write_double_be(fake, kAxisMin, m.offset_mm);
    write_double_be(fake, kAxisMax, m.offset_mm + 65535.0 * m.scale_mm);
    write_double_be(fake, kFocal, m.focal_px);
    write_double_be(fake, kPpu, m.cx_px);
    write_double_be(fake, kPpv, m.cy_px);
    arv_fake_camera_set_trigger_frequency(fake, 200.0);  // poll the software trigger every 5 ms
    render(0.0);
    arv_fake_camera_set_fill_pattern(fake, &Impl::fill_pattern, this);
    logger()->info("simulated camera {} serial {} listening on {} (GigE Vision), {}x{} Coord3D_C16, scene: {}",
                   m.width * m.height >= 3000000 ? "3.2 MP" : "", options.serial, options.address, m.width, m.height,
                   source.description);
  }

  ~Impl() { cleanup(); }
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;

  void cleanup() {
    if (gv != nullptr) g_object_unref(gv);  // joins the camera thread
    gv = nullptr;
    fake = nullptr;
    std::error_code ec;
    std::filesystem::remove(xml_file, ec);
  }

  static void fill_pattern(ArvBuffer* buffer, void* self, guint32 /*exposure_us*/, guint32 /*gain*/,
                           ArvPixelFormat pixel_format) {
    static_cast<Impl*>(self)->fill(buffer, static_cast<std::uint32_t>(pixel_format));
  }

  void fill(ArvBuffer* buffer, std::uint32_t pixel_format) {
    const std::uint64_t n = sent++;
    double ratio = base_loss;
    if (drop > 0) {
      --drop;
      ratio = 1.0;
      logger()->info("simulated camera: dropping frame {} (injected stall)", n);
    } else if (loss_frames > 0) {
      --loss_frames;
      ratio = loss_ratio;
      logger()->info("simulated camera: frame {} loses packets with ratio {}", n, ratio);
    }
    g_object_set(gv, "gvsp-lost-ratio", ratio, nullptr);
    if (const int ms = stall_ms.exchange(0); ms > 0) {
      logger()->info("simulated camera: stalling {} ms before frame {}", ms, n);
      std::this_thread::sleep_for(std::chrono::milliseconds(ms));
    }

    const auto& m = source.model;
    std::shared_ptr<const std::vector<std::uint16_t>> current;
    {
      std::lock_guard lock(image_mutex);
      current = image;
    }
    if (!current) return;
    const std::vector<std::uint16_t>& range = *current;
    const auto w = static_cast<std::uint32_t>(arv_buffer_get_image_width(buffer));
    const auto h = static_cast<std::uint32_t>(arv_buffer_get_image_height(buffer));
    if (w != m.width || h != m.height || range.size() != std::size_t{w} * h) return;
    // The fake camera allocated the buffer for this payload (it checks the size before calling us).
    auto* data = static_cast<unsigned char*>(const_cast<void*>(arv_buffer_get_data(buffer, nullptr)));
    if (data == nullptr) return;
    const std::size_t count = range.size();
    const float nan = std::numeric_limits<float>::quiet_NaN();
    auto z_of = [&](std::uint16_t raw) {
      return raw == m.invalid ? nan : static_cast<float>(raw * m.scale_mm + m.offset_mm);
    };
    switch (pixel_format) {
      case kCoord3D_C16:
        std::memcpy(data, range.data(), count * 2);
        break;
      case kCoord3D_C32f:
        for (std::size_t i = 0; i < count; ++i) {
          const float z = z_of(range[i]);
          std::memcpy(data + i * 4, &z, 4);
        }
        break;
      case kCoord3D_ABC32f:
        for (std::uint32_t v = 0; v < h; ++v)
          for (std::uint32_t u = 0; u < w; ++u) {
            const std::size_t i = std::size_t{v} * w + u;
            const float z = z_of(range[i]);
            const float xyz[3] = {static_cast<float>((u - m.cx_px) / m.focal_px * z),
                                  static_cast<float>((v - m.cy_px) / m.focal_px * z), z};
            std::memcpy(data + i * 12, xyz, 12);
          }
        break;
      case kMono8:  // an intensity view: near is bright
        for (std::size_t i = 0; i < count; ++i)
          data[i] = range[i] == m.invalid ? 0 : static_cast<unsigned char>(255 - (range[i] >> 8));
        break;
      default:
        break;
    }
  }
};

SimulatedCamera::SimulatedCamera(SimulatedCameraOptions options, RangeImageSource source)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(source))) {}
SimulatedCamera::~SimulatedCamera() = default;
const std::string& SimulatedCamera::address() const { return impl_->options.address; }
const RangeImageModel& SimulatedCamera::model() const { return impl_->source.model; }
void SimulatedCamera::set_slide_position_mm(double slide_mm) { impl_->render(slide_mm); }
double SimulatedCamera::slide_position_mm() const { return impl_->slide_mm; }
void SimulatedCamera::drop_frames(int frames) { impl_->drop = frames; }
void SimulatedCamera::lose_packets(int frames, double ratio) {
  impl_->loss_ratio = ratio;
  impl_->loss_frames = frames;
}
void SimulatedCamera::set_packet_loss(double ratio) { impl_->base_loss = ratio; }
void SimulatedCamera::stall_next_frame_ms(int ms) { impl_->stall_ms = ms; }
void SimulatedCamera::revoke_control() { arv_fake_camera_set_control_channel_privilege(impl_->fake, 0); }
void SimulatedCamera::stop_acquisition() {
  arv_fake_camera_write_register(impl_->fake, ARV_FAKE_CAMERA_REGISTER_ACQUISITION, 0);
}
std::uint64_t SimulatedCamera::frames_sent() const { return impl_->sent; }

}  // namespace fettle::sim
