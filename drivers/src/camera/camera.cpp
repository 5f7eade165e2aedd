// The GigE Vision 3D camera through Aravis (see camera.hpp).
#include "fettle/drivers/camera.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <arv.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <sstream>
#include <utility>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"

namespace fettle::drivers {
namespace {

auto logger() { return log::get("camera"); }

template <class T>
struct GObjectUnref {
  void operator()(T* p) const {
    if (p != nullptr) g_object_unref(p);
  }
};
template <class T>
using GPtr = std::unique_ptr<T, GObjectUnref<T>>;

/// Takes a GError's message and frees it.
std::string take(GError*& e) {
  std::string m = e != nullptr && e->message != nullptr ? e->message : "unknown error";
  g_clear_error(&e);
  return m;
}

double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

/// The local IPv4 address the kernel would use to reach `address` (no packet is sent).
std::string local_address_for(const std::string& address) {
  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  if (fd < 0) throw DeviceError("camera " + address + ": cannot create a UDP socket: " + std::strerror(errno));
  sockaddr_in peer{};
  peer.sin_family = AF_INET;
  peer.sin_port = htons(3956);
  if (::inet_pton(AF_INET, address.c_str(), &peer.sin_addr) != 1) {
    ::close(fd);
    throw UserError("camera address '" + address + "' is not an IPv4 address");
  }
  sockaddr_in local{};
  socklen_t len = sizeof local;
  const bool ok = ::connect(fd, reinterpret_cast<sockaddr*>(&peer), sizeof peer) == 0 &&
                  ::getsockname(fd, reinterpret_cast<sockaddr*>(&local), &len) == 0;
  const int err = errno;
  ::close(fd);
  if (!ok)
    throw DeviceError("camera " + address + ": no route to the camera (" + std::strerror(err) +
                      "); check the network interface and the address in [camera]");
  char buf[INET_ADDRSTRLEN];
  ::inet_ntop(AF_INET, &local.sin_addr, buf, sizeof buf);
  return buf;
}

/// The address of the camera with `serial`, by GigE Vision discovery (the only discovery the
/// cell does, and only when the config names a serial instead of an address).
std::string address_for_serial(const std::string& serial) {
  logger()->warn("camera: looking for serial {} by GigE Vision discovery; set [camera] address to avoid it", serial);
  arv_update_device_list();
  const unsigned n = arv_get_n_devices();
  for (unsigned i = 0; i < n; ++i) {
    const char* s = arv_get_device_serial_nbr(i);
    const char* protocol = arv_get_device_protocol(i);
    const char* a = arv_get_device_address(i);
    if (s != nullptr && serial == s && protocol != nullptr && std::string(protocol) == "GigEVision" && a != nullptr) {
      logger()->info("camera: serial {} is at {}", serial, a);
      return a;
    }
  }
  throw DeviceError("camera with serial '" + serial + "' not found by GigE Vision discovery (" + std::to_string(n) +
                    " devices answered); check power and cabling, or set [camera] address");
}

extern "C" void on_control_lost(ArvDevice* /*device*/, gpointer flag) {
  static_cast<std::atomic<bool>*>(flag)->store(true);
}

}  // namespace

CameraOptions camera_options(const config::CameraSection& s) {
  CameraOptions o;
  o.address = s.address;
  o.serial = s.serial;
  o.frame_timeout_ms = s.frame_timeout_ms;
  o.retries = s.retries;
  o.exposure_us = s.exposure_us;
  o.pixel_format = s.pixel_format;
  o.packet_size_bytes = s.packet_size_bytes;
  return o;
}

std::string CameraInfo::to_string() const {
  std::ostringstream s;
  s << "vendor:        " << vendor << "\nmodel:         " << model << "\nserial:        " << serial
    << "\naddress:       " << address << "\nimage:         " << width << " x " << height << " px"
    << "\npixel format:  " << pixel_format << "\noffered:      ";
  for (const auto& f : pixel_formats) s << " " << f;
  s << "\npacket size:   " << packet_size_bytes << " bytes";
  if (exposure_us > 0.0) s << "\nexposure:      " << exposure_us << " us";
  if (heartbeat_timeout_ms > 0) s << "\nheartbeat:     " << heartbeat_timeout_ms << " ms timeout";
  s << "\nScan3d:        " << (scan3d_from_camera ? "yes" : "no (not a GenICam SFNC 3D camera)");
  if (scan3d_from_camera) {
    s << "\n  scale:       " << scan3d.scale << "\n  offset:      " << scan3d.offset << "\n  unit:        "
      << scan3d.unit_mm << " mm\n  invalid:     ";
    if (scan3d.invalid_data_flag)
      s << scan3d.invalid_data_value;
    else
      s << "(none)";
  }
  s << "\nintrinsics:    " << intrinsics_source;
  if (scan3d.intrinsics)
    s << " (fx " << scan3d.intrinsics->fx_px << " fy " << scan3d.intrinsics->fy_px << " cx "
      << scan3d.intrinsics->cx_px << " cy " << scan3d.intrinsics->cy_px << " px)";
  s << "\n";
  return s.str();
}

struct Camera::Impl {
  CameraOptions options;
  std::string address;  ///< resolved
  CameraInfo info;
  GPtr<ArvCamera> camera;
  GPtr<ArvStream> stream;
  gulong control_lost_handler = 0;
  ArvDevice* device = nullptr;  ///< owned by camera
  std::atomic<bool> control_lost{false};
  /// The last capture got no complete frame: the next one starts with a fresh camera and stream.
  /// Whatever stopped the frames (the camera dropped our control after a heartbeat gap without
  /// Aravis noticing, a stream socket gone bad, a camera rebooted between two heartbeats), a new
  /// connection clears it; a camera that is merely losing packets costs one reconnect.
  bool reopen = false;
  int reconnects = 0;
  OrganizedCloud scratch;

  explicit Impl(CameraOptions o) : options(std::move(o)) {
    address = !options.address.empty() ? options.address : address_for_serial(options.serial);
    open();
  }
  ~Impl() { close(); }
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;

  [[noreturn]] void fail(const std::string& what, GError*& e) {
    const std::string m = take(e);
    close();
    throw DeviceError("camera " + address + ": " + what + ": " + m);
  }

  bool implemented(const char* feature) {
    GError* e = nullptr;
    const bool yes = arv_camera_is_feature_available(camera.get(), feature, &e) != FALSE;
    g_clear_error(&e);
    return yes;
  }
  std::optional<double> read_float(const char* feature) {
    if (!implemented(feature)) return std::nullopt;
    GError* e = nullptr;
    const double v = arv_camera_get_float(camera.get(), feature, &e);
    if (e != nullptr) {
      logger()->warn("camera {}: cannot read {}: {}", address, feature, take(e));
      return std::nullopt;
    }
    return v;
  }
  std::string read_string(const char* feature) {
    if (!implemented(feature)) return {};
    GError* e = nullptr;
    const char* v = arv_camera_get_string(camera.get(), feature, &e);
    if (e != nullptr) {
      g_clear_error(&e);
      return {};
    }
    return v != nullptr ? v : "";
  }
  void set_string(const char* feature, const char* value) {
    GError* e = nullptr;
    arv_camera_set_string(camera.get(), feature, value, &e);
    if (e != nullptr) fail(std::string("cannot set ") + feature + " to " + value, e);
  }

  void open() {
    const auto t0 = std::chrono::steady_clock::now();
    const std::string local = local_address_for(address);
    GPtr<GInetAddress> iface(g_inet_address_new_from_string(local.c_str()));
    GPtr<GInetAddress> device_address(g_inet_address_new_from_string(address.c_str()));
    GError* e = nullptr;
    // Unicast only: the device is opened at its address, never looked up by discovery.
    GPtr<ArvDevice> dev(arv_gv_device_new(iface.get(), device_address.get(), &e));
    if (e != nullptr || !dev) {
      const std::string m = take(e);
      throw DeviceError("camera " + address + ": cannot open the GigE Vision camera (control channel UDP 3956 from " +
                        local + "): " + m +
                        "; check that it is powered, the address in [camera] and that no other program controls it");
    }
    camera.reset(arv_camera_new_with_device(dev.get(), &e));
    if (e != nullptr || !camera) fail("cannot read its GenICam description", e);
    device = arv_camera_get_device(camera.get());
    control_lost = false;
    control_lost_handler = g_signal_connect_data(device, "control-lost", reinterpret_cast<GCallback>(&on_control_lost),
                                                 &control_lost, nullptr, G_CONNECT_DEFAULT);
    configure();
    logger()->info("camera {}: {} {} serial {} open in {:.0f} ms, {}x{} {}", address, info.vendor, info.model,
                   info.serial, ms_since(t0), info.width, info.height, info.pixel_format);
  }

  void configure() {
    ArvCamera* c = camera.get();
    GError* e = nullptr;
    info.address = address;
    info.vendor = read_string("DeviceVendorName");
    info.model = read_string("DeviceModelName");
    const char* serial = arv_camera_get_device_serial_number(c, &e);
    info.serial = serial != nullptr ? serial : "";
    g_clear_error(&e);

    arv_camera_stop_acquisition(c, &e);  // a previous controller may have left it running
    g_clear_error(&e);
    if (!options.pixel_format.empty()) {
      arv_camera_set_pixel_format_from_string(c, options.pixel_format.c_str(), &e);
      if (e != nullptr) fail("cannot set PixelFormat to " + options.pixel_format, e);
    }
    if (options.packet_size_bytes > 0) {
      arv_camera_gv_set_packet_size(c, options.packet_size_bytes, &e);
      if (e != nullptr) fail("cannot set the packet size to " + std::to_string(options.packet_size_bytes), e);
    }
    if (options.heartbeat_timeout_ms > 0) {
      if (implemented("GevHeartbeatTimeout")) {
        arv_camera_set_integer(c, "GevHeartbeatTimeout", options.heartbeat_timeout_ms, &e);
        if (e != nullptr)
          fail("cannot set GevHeartbeatTimeout to " + std::to_string(options.heartbeat_timeout_ms) + " ms", e);
      } else {
        logger()->warn("camera {}: has no GevHeartbeatTimeout feature; heartbeat_timeout_ms ignored", address);
      }
    }
    if (options.exposure_us > 0.0) {
      if (arv_camera_is_exposure_time_available(c, &e) != FALSE) {
        arv_camera_set_exposure_time(c, options.exposure_us, &e);
        if (e != nullptr) fail("cannot set the exposure time to " + std::to_string(options.exposure_us) + " us", e);
      } else {
        g_clear_error(&e);
        logger()->warn("camera {}: has no exposure time feature; exposure_us ignored", address);
      }
    }
    // One frame per software trigger, acquisition running continuously.
    if (implemented("AcquisitionMode")) set_string("AcquisitionMode", "Continuous");
    if (!implemented("TriggerMode") || !implemented("TriggerSoftware"))
      throw DeviceError("camera " + address + ": has no software trigger (TriggerMode/TriggerSoftware features)");
    if (implemented("TriggerSelector")) set_string("TriggerSelector", "FrameStart");
    set_string("TriggerMode", "On");
    if (implemented("TriggerSource")) set_string("TriggerSource", "Software");

    gint x = 0, y = 0, w = 0, h = 0;
    arv_camera_get_region(c, &x, &y, &w, &h, &e);
    if (e != nullptr) fail("cannot read the image size", e);
    info.width = static_cast<std::uint32_t>(w);
    info.height = static_cast<std::uint32_t>(h);
    const char* pf = arv_camera_get_pixel_format_as_string(c, &e);
    info.pixel_format = pf != nullptr ? pf : "";
    g_clear_error(&e);
    guint n = 0;
    const char** formats = arv_camera_dup_available_pixel_formats_as_strings(c, &n, &e);
    g_clear_error(&e);
    info.pixel_formats.clear();
    for (guint i = 0; formats != nullptr && i < n; ++i) info.pixel_formats.emplace_back(formats[i]);
    g_free(static_cast<void*>(formats));
    info.packet_size_bytes = arv_camera_gv_get_packet_size(c, &e);
    g_clear_error(&e);
    if (arv_camera_is_exposure_time_available(c, &e) != FALSE) info.exposure_us = arv_camera_get_exposure_time(c, &e);
    g_clear_error(&e);
    if (implemented("GevHeartbeatTimeout")) info.heartbeat_timeout_ms = arv_camera_get_integer(c, "GevHeartbeatTimeout", &e);
    g_clear_error(&e);

    read_scan3d();
    const auto code = pixel_format_from_name(info.pixel_format);
    if (!code || !is_supported_pixel_format(*code))
      logger()->warn("camera {}: pixel format {} is not 3D data (Coord3D_C16, Coord3D_C32f, Coord3D_ABC32f): "
                     "captures will fail; set [camera] pixel_format",
                     address, info.pixel_format);

    create_stream();
    arv_camera_start_acquisition(c, &e);
    if (e != nullptr) fail("cannot start acquisition", e);
  }

  void read_scan3d() {
    Scan3dParameters& p = info.scan3d;
    p = Scan3dParameters{};
    info.scan3d_from_camera = implemented("Scan3dCoordinateScale");
    if (implemented("Scan3dCoordinateSelector")) {
      GError* e = nullptr;
      arv_camera_set_string(camera.get(), "Scan3dCoordinateSelector", "CoordinateC", &e);
      if (e != nullptr) logger()->warn("camera {}: cannot select CoordinateC: {}", address, take(e));
    }
    if (auto v = read_float("Scan3dCoordinateScale")) p.scale = *v;
    if (auto v = read_float("Scan3dCoordinateOffset")) p.offset = *v;
    if (implemented("Scan3dInvalidDataFlag")) {
      GError* e = nullptr;
      p.invalid_data_flag = arv_camera_get_boolean(camera.get(), "Scan3dInvalidDataFlag", &e) != FALSE;
      g_clear_error(&e);
    }
    if (auto v = read_float("Scan3dInvalidDataValue")) {
      p.invalid_data_value = *v;
      if (!implemented("Scan3dInvalidDataFlag")) p.invalid_data_flag = true;
    }
    const std::string unit = read_string("Scan3dDistanceUnit");
    if (unit == "Inch") p.unit_mm = 25.4;
    else if (unit == "Meter") p.unit_mm = 1000.0;
    else if (!unit.empty() && unit != "Millimeter")
      logger()->warn("camera {}: unknown Scan3dDistanceUnit {}, assuming millimetres", address, unit);
    if (options.intrinsics) {
      p.intrinsics = options.intrinsics;
      info.intrinsics_source = "calibration";
      return;
    }
    const auto f = read_float("Scan3dFocalLength");
    const auto u = read_float("Scan3dPrincipalPointU");
    const auto v = read_float("Scan3dPrincipalPointV");
    if (f && u && v && *f > 0.0) {
      p.intrinsics = Intrinsics{*f, *f, *u, *v};
      info.intrinsics_source = "camera";
    } else {
      info.intrinsics_source = "none";
    }
  }

  void create_stream() {
    GError* e = nullptr;
    stream.reset(arv_camera_create_stream(camera.get(), nullptr, nullptr, &e));
    if (e != nullptr || !stream) fail("cannot create the stream channel", e);
    if (ARV_IS_GV_STREAM(stream.get()))
      g_object_set(stream.get(), "packet-resend", ARV_GV_STREAM_PACKET_RESEND_ALWAYS, "socket-buffer",
                   ARV_GV_STREAM_SOCKET_BUFFER_AUTO, nullptr);
    const guint payload = arv_camera_get_payload(camera.get(), &e);
    if (e != nullptr) fail("cannot read PayloadSize", e);
    for (int i = 0; i < 3; ++i) arv_stream_push_buffer(stream.get(), arv_buffer_new_allocate(payload));
  }

  void close() {
    if (camera) {
      GError* e = nullptr;
      if (!control_lost) arv_camera_stop_acquisition(camera.get(), &e);
      g_clear_error(&e);
    }
    stream.reset();
    if (device != nullptr && control_lost_handler != 0) g_signal_handler_disconnect(device, control_lost_handler);
    control_lost_handler = 0;
    device = nullptr;
    camera.reset();
  }

  /// Tears down the camera and the stream and opens them again.
  Status recreate() {
    const bool lost = control_lost;
    logger()->warn("camera {}: {}; recreating the camera and its stream", address,
                   lost ? "control lost" : "the last capture got no complete frame");
    close();
    try {
      open();
    } catch (const Exception& ex) {
      control_lost = true;
      return Error{"camera.control_lost", std::string(lost ? "control of the camera was lost" : "the camera sent no frame") +
                                              " and reconnecting failed: " + ex.what(), ErrorKind::unavailable};
    }
    reopen = false;
    ++reconnects;
    return {};
  }

  struct Counters {
    guint64 completed = 0, failures = 0, underruns = 0, resent = 0, missing = 0;
  };
  Counters counters() {
    Counters c;
    if (!stream) return c;
    arv_stream_get_statistics(stream.get(), &c.completed, &c.failures, &c.underruns);
    if (ARV_IS_GV_STREAM(stream.get())) arv_gv_stream_get_statistics(ARV_GV_STREAM(stream.get()), &c.resent, &c.missing);
    return c;
  }

  /// Gives back frames that arrived after an earlier attempt gave up on them.
  void drain() {
    while (ArvBuffer* b = arv_stream_try_pop_buffer(stream.get())) {
      logger()->debug("camera {}: discarding late frame {}", address, arv_buffer_get_frame_id(b));
      arv_stream_push_buffer(stream.get(), b);
    }
  }

  Status capture(CameraCapture& out) {
    CaptureStats st;
    if (control_lost || reopen) {
      if (auto s = recreate(); !s) return s.error();
      st.reconnected = true;
    }
    const Counters before = counters();
    auto finish_stats = [&](CaptureStats& s) {
      const Counters after = counters();
      s.resent_packets = after.resent - before.resent;
      s.missing_packets = after.missing - before.missing;
      s.underruns = after.underruns - before.underruns;
      s.failed_frames = after.failures - before.failures;
    };
    std::string last;
    const int attempts = 1 + std::max(0, options.retries);
    for (int attempt = 1; attempt <= attempts; ++attempt) {
      if (control_lost) {
        if (auto s = recreate(); !s) return s.error();
        st.reconnected = true;
      }
      drain();
      ++st.attempts;
      const auto t0 = std::chrono::steady_clock::now();
      GError* e = nullptr;
      arv_camera_software_trigger(camera.get(), &e);
      if (e != nullptr) {
        last = "software trigger failed: " + take(e);
        logger()->warn("camera {}: attempt {}/{}: {}", address, attempt, attempts, last);
        continue;
      }
      ArvBuffer* b = arv_stream_timeout_pop_buffer(stream.get(), static_cast<guint64>(options.frame_timeout_ms) * 1000);
      if (b == nullptr) {
        last = "no frame within " + std::to_string(options.frame_timeout_ms) + " ms";
        logger()->warn("camera {}: attempt {}/{}: {}", address, attempt, attempts, last);
        continue;
      }
      const ArvBufferStatus status = arv_buffer_get_status(b);
      if (status != ARV_BUFFER_STATUS_SUCCESS) {
        last = status == ARV_BUFFER_STATUS_MISSING_PACKETS ? "frame incomplete (missing packets)"
               : status == ARV_BUFFER_STATUS_TIMEOUT       ? "frame incomplete (packet timeout)"
                                                           : "frame failed (buffer status " +
                                                                 std::to_string(static_cast<int>(status)) + ")";
        arv_stream_push_buffer(stream.get(), b);
        logger()->warn("camera {}: attempt {}/{}: {}", address, attempt, attempts, last);
        continue;
      }
      st.wait_ms = ms_since(t0);
      const auto t1 = std::chrono::steady_clock::now();
      size_t size = 0;
      const void* data = arv_buffer_get_image_data(b, &size);
      RawFrame frame{static_cast<std::uint32_t>(arv_buffer_get_image_pixel_format(b)),
                     static_cast<std::uint32_t>(arv_buffer_get_image_width(b)),
                     static_cast<std::uint32_t>(arv_buffer_get_image_height(b)), static_cast<const std::byte*>(data),
                     size};
      out.frame_id = arv_buffer_get_frame_id(b);
      out.timestamp_ns = arv_buffer_get_timestamp(b);
      out.pixel_format = frame.pixel_format;
      Status decoded = decode_frame(frame, info.scan3d, out.cloud);
      arv_stream_push_buffer(stream.get(), b);
      st.decode_ms = ms_since(t1);
      finish_stats(st);
      if (!decoded) {
        logger()->error("camera {}: {}", address, decoded.error().message);
        return Error{decoded.error().code, "camera " + address + ": " + decoded.error().message, decoded.error().kind};
      }
      out.stats = st;
      logger()->info(
          "camera {}: frame {} {}x{} in {:.0f} ms (decode {:.1f} ms), attempts {}, resent packets {}, missing "
          "packets {}, underruns {}",
          address, out.frame_id, frame.width, frame.height, st.wait_ms, st.decode_ms, st.attempts, st.resent_packets,
          st.missing_packets, st.underruns);
      return {};
    }
    finish_stats(st);
    reopen = true;
    logger()->error("camera {}: fault after {} attempts (last: {}); resent packets {}, missing packets {}, underruns {}",
                    address, st.attempts, last, st.resent_packets, st.missing_packets, st.underruns);
    return Error{"camera.fault", "camera " + address + ": no complete frame after " + std::to_string(st.attempts) +
                                     " attempts (last: " + last +
                                     "); check the cable and the network interface (packet loss), or raise "
                                     "[camera] frame_timeout_ms / retries", ErrorKind::no_data};
  }
};

Camera::Camera(CameraOptions options) : impl_(std::make_unique<Impl>(std::move(options))) {}
Camera::~Camera() = default;
const CameraInfo& Camera::info() const { return impl_->info; }
Result<CameraCapture> Camera::capture() {
  CameraCapture out;
  if (auto s = impl_->capture(out); !s) return s.error();
  return out;
}
Status Camera::capture(CameraCapture& out) { return impl_->capture(out); }
bool Camera::control_lost() const { return impl_->control_lost; }
int Camera::reconnects() const { return impl_->reconnects; }

std::vector<DiscoveredCamera> discover_cameras() {
  arv_update_device_list();
  std::vector<DiscoveredCamera> out;
  const unsigned n = arv_get_n_devices();
  auto s = [](const char* p) { return std::string(p != nullptr ? p : ""); };
  for (unsigned i = 0; i < n; ++i)
    out.push_back(DiscoveredCamera{s(arv_get_device_id(i)), s(arv_get_device_vendor(i)), s(arv_get_device_model(i)),
                                   s(arv_get_device_serial_nbr(i)), s(arv_get_device_address(i)),
                                   s(arv_get_device_protocol(i))});
  return out;
}

}  // namespace fettle::drivers
