// The simulated cell (cell.hpp): PLC, camera, robot and spindle around one casting.
#include "fettle/sim/cell.hpp"

#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>
#include <thread>
#include <utility>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/thread_pool.hpp>

#include "fettle/config/calibration.hpp"
#include "fettle/config/load.hpp"
#include "fettle/config/roi.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/drivers/canopen_transport.hpp"
#include "fettle/drivers/robot_protocol.hpp"
#include "fettle/sim/camera.hpp"
#include "fettle/sim/errors.hpp"
#include "fettle/sim/robot.hpp"
#include "fettle/sim/sim.hpp"
#include "fettle/sim/spindle.hpp"

namespace fettle::sim {

namespace asio = boost::asio;
using Clock = std::chrono::steady_clock;

struct CellSim::Impl : std::enable_shared_from_this<CellSim::Impl> {
  explicit Impl(CellSimOptions o) : options(std::move(o)), log(log::get("sim.cell")) {}

  CellSimOptions options;
  std::shared_ptr<spdlog::logger> log;
  config::PartRecipe recipe;
  int recipe_id = 1;

  asio::io_context io;
  std::optional<asio::executor_work_guard<asio::io_context::executor_type>> work;
  std::thread io_thread;
  asio::thread_pool grinder{1};

  std::unique_ptr<PlcSimulator> plc;
  std::unique_ptr<RobotSim> robot;
  std::shared_ptr<canopen::InProcessBus> bus;
  std::unique_ptr<SimulatedSpindleDrive> drive;
  std::unique_ptr<SocketcandServer> socketcand;
  std::unique_ptr<SimulatedCamera> camera;

  // The casting on the fixture (guarded by casting_mutex).
  mutable std::mutex casting_mutex;
  std::optional<Casting> casting;
  /// What the camera sees while the fixture is empty: the last casting's scene without it.
  std::optional<Casting> empty_scene;
  std::atomic<std::uint64_t> casting_version{0};
  std::unique_ptr<Scanner> scanner;
  ScannerConfig nominal;                  ///< the scanner as the cell believes it is (what the camera reports)
  std::optional<CellErrors> drawn;        ///< --errors: this cell's errors
  config::PartRecipe world;               ///< the castings' recipe: the cell's, with the budget's form deviation
  std::map<std::string, double> worn_mm;  ///< --errors: each tool's radius lost to wear (grinder thread)
  std::size_t views_rendered = 0;

  // Rendering on slide arrival.
  std::mutex render_mutex;
  std::condition_variable render_cv;
  std::optional<std::pair<double, std::uint64_t>> render_request;  // (slide mm, casting version)
  std::pair<double, std::uint64_t> rendered{NAN, 0};
  std::thread render_thread;

  // Supervisor.
  std::atomic<bool> stopping{false};
  std::thread supervisor;
  std::atomic<bool> auto_start{true};
  std::atomic<std::size_t> results_seen{0};
  std::atomic<int> finished{0};  ///< fed castings whose cycle ended with a result other than FAULT
  int fed = 0;
  bool part_in_progress = false;
  bool stays = false;  ///< the fed casting's cycle ended FAULT: it stays on the fixture, requested again
  Clock::time_point last_command_at{};
  std::mutex handler_mutex;
  CellEventHandler handler;

  void event(const std::string& line) {
    log->info("{}", line);
    std::lock_guard lock(handler_mutex);
    if (handler) handler(line);
  }

  // ---- setup ----

  /// The scanner as it really is; sets `nominal` (and `drawn` with --errors) on the way.
  ScannerConfig scanner_config() {
    ScannerConfig c;
    c.intrinsics = c.intrinsics.scaled(static_cast<int>(options.camera_width), static_cast<int>(options.camera_height));
    c.intrinsics.k1 = c.intrinsics.k2 = c.intrinsics.p1 = c.intrinsics.p2 = c.intrinsics.k3 = 0.0;  // rectified range maps
    c.intrinsics.fy = c.intrinsics.fx;
    c.noise.enabled = options.noise;
    c.place_in_cell(options.cell);  // where the cell's calibration says the camera is
    nominal = c;
    if (!options.errors) return c;
    drawn = draw_cell_errors(*options.errors, options.cell_seed, c);
    return true_scanner(c, *drawn);  // where it really is
  }

  RangeImageSource range_source() {
    RangeImageModel model;
    const auto& in = nominal.intrinsics;  // what the camera tells fettled
    model.width = static_cast<std::uint32_t>(in.width);
    model.height = static_cast<std::uint32_t>(in.height);
    model.focal_px = in.fx;
    model.cx_px = in.cx;
    model.cy_px = in.cy;
    RangeImageSource src;
    src.model = model;
    src.description = "the casting on the fixture (fettle-sim cell)";
    auto weak = weak_from_this();
    src.render = [weak, model](double slide_mm, std::vector<std::uint16_t>& out) {
      out.assign(std::size_t{model.width} * model.height, model.invalid);
      auto self = weak.lock();
      if (!self) return;
      std::lock_guard lock(self->casting_mutex);
      if (!self->casting && !self->empty_scene) {  // nothing loaded yet: a seed-0 scene, without its part
        self->empty_scene = Casting::make(self->world, 0);
        self->empty_scene->take_off_fixture();
      }
      const Casting& scene = self->casting ? *self->casting : *self->empty_scene;
      const std::size_t view = self->views_rendered++;
      const auto& e = self->drawn;
      const double true_mm = slide_mm + (e ? e->slide_error_mm(scene.seed(), view) : 0.0);
      Capture capture = self->scanner->capture(scene, true_mm, view);
      if (e) e->add_correlated_depth(capture.range);
      const auto& z = capture.range;
      if (z.width != model.width || z.height != model.height) return;
      for (std::size_t i = 0; i < out.size(); ++i) {
        const float v = z.data[i];
        if (!std::isfinite(v)) continue;
        const double raw = std::round((v - model.offset_mm) / model.scale_mm);
        if (raw >= 1.0 && raw <= 65535.0) out[i] = static_cast<std::uint16_t>(raw);
      }
    };
    return src;
  }

  void start() {
    const auto& cell = options.cell;
    if (cell.cell.recipes.empty()) throw UserError(cell.source.string() + ": [[cell.recipes]] is empty");
    const config::RecipeRef* ref = &cell.cell.recipes.front();
    for (const auto& r : cell.cell.recipes)
      if (r.plc_recipe_id == options.recipe_id) ref = &r;
    recipe = config::load_part(ref->file);
    recipe_id = ref->plc_recipe_id;
    world = recipe;
    if (options.errors && options.errors->form_deviation_mm)
      world.geometry.variation.form_deviation_mm = *options.errors->form_deviation_mm;
    scanner = std::make_unique<Scanner>(scanner_config());
    if (drawn) event("errors from " + options.errors->source.string() + ", drawn for cell seed " +
                     std::to_string(options.cell_seed) + ": " + drawn->to_json()["drawn"].dump());
    auto_start = options.auto_start;

    PlcSimOptions po;
    po.address = options.address;
    po.port = options.plc_port >= 0 ? options.plc_port : cell.plc.port;
    po.register_base = cell.plc.register_base;
    po.photo_positions_mm = cell.slide.photo_positions_mm;
    po.home_mm = cell.slide.home_mm;
    po.slide_speed_mm_s = options.slide_speed_mm_s;
    plc = std::make_unique<PlcSimulator>(po);
    auto weak = weak_from_this();
    plc->set_slide_gate([weak](int position, double mm) {
      auto self = weak.lock();
      return !self || self->gate(position, mm);
    });
    plc->start();

    RobotSimOptions ro;
    ro.address = options.address;
    ro.port = options.robot_port >= 0 ? options.robot_port : cell.robot.port;
    ro.expected_cell_id = cell.robot.cell_id;
    ro.speedup = options.robot_speedup;
    const auto& s = cell.safety;
    ro.envelope.min_mm = s.workspace_min_mm;
    ro.envelope.max_mm = s.workspace_max_mm;
    ro.envelope.max_speed_mm_s = s.max_speed_mm_s;
    ro.envelope.max_spindle_rpm = s.max_spindle_rpm;
    robot = std::make_unique<RobotSim>(io, ro);
    // The casting is ground before the robot reports DONE (the grinding simulation takes real
    // time; the verification scan must see the ground part).
    robot->on_settle([weak](const Trajectory& t, std::function<void()> done) {
      if (auto self = weak.lock()) self->executed(t, std::move(done));
      else done();
    });
    robot->start();

    bus = canopen::InProcessBus::create();
    SpindleSimOptions so;
    so.node_id = static_cast<std::uint8_t>(cell.spindle.node_id);
    so.max_rpm = cell.spindle.max_rpm;
    drive = std::make_unique<SimulatedSpindleDrive>(io, bus->attach(io, "drive"), so);
    socketcand = std::make_unique<SocketcandServer>(
        io, bus, options.address, options.spindle_port >= 0 ? options.spindle_port : cell.spindle.port,
        cell.spindle.interface);
    drive->power_on();

    work.emplace(io.get_executor());
    io_thread = std::thread([this] { io.run(); });

    if (options.camera) {
      SimulatedCameraOptions co;
      co.address = options.address;
      camera = std::make_unique<SimulatedCamera>(co, range_source());
    }
    render_thread = std::thread([this] { render_loop(); });
    supervisor = std::thread([this] { supervise(); });
    event("cell ready: PLC " + options.address + ":" + std::to_string(plc->port()) + ", robot " + options.address +
          ":" + std::to_string(robot_port()) + ", spindle socketcand " + options.address + ":" +
          std::to_string(socketcand->port()) + " bus " + cell.spindle.interface +
          (camera ? ", camera " + options.address + " (UDP 3956)" : ", no camera"));
  }

  /// Runs `f` on the devices' io thread and returns its value (members of RobotSim and the drive
  /// live there). Waits at most 2 s (a T{} then); the shared state outlives a late handler.
  template <class T>
  T on_io(std::function<T()> f) const {
    struct Shared {
      std::mutex m;
      std::condition_variable cv;
      bool done = false;
      T value{};
    };
    auto sh = std::make_shared<Shared>();
    asio::post(const_cast<asio::io_context&>(io), [sh, f = std::move(f)] {
      T v = f();
      std::lock_guard l(sh->m);
      sh->value = std::move(v);
      sh->done = true;
      sh->cv.notify_all();
    });
    std::unique_lock l(sh->m);
    sh->cv.wait_for(l, std::chrono::seconds(2), [&] { return sh->done; });
    return sh->value;
  }
  int robot_port() const { return on_io<int>([this] { return robot->port(); }); }

  void stop() {
    if (stopping.exchange(true)) return;
    render_cv.notify_all();
    if (supervisor.joinable()) supervisor.join();
    if (render_thread.joinable()) render_thread.join();
    if (plc) plc->stop();
    grinder.join();
    asio::post(io, [this] {
      if (robot) robot->close();
      socketcand.reset();
      work.reset();
      io.stop();  // the drive's and the robot's timers would keep run() going
    });
    if (io_thread.joinable()) io_thread.join();
    camera.reset();
  }

  // ---- camera images follow the slide ----

  /// PLC thread, with its lock held: true once the image for this position is ready.
  bool gate(int position, double mm) {
    if (position == 0 || !camera) return true;
    const std::uint64_t version = casting_version;  // atomic: grinding holds casting_mutex for a while
    std::lock_guard lock(render_mutex);
    if (rendered.first == mm && rendered.second == version) return true;
    if (!render_request || render_request->first != mm || render_request->second != version) {
      render_request = std::make_pair(mm, version);
      render_cv.notify_all();
    }
    return false;
  }

  void render_loop() {
    while (!stopping) {
      std::pair<double, std::uint64_t> req;
      {
        std::unique_lock lock(render_mutex);
        render_cv.wait(lock, [this] { return stopping || render_request.has_value(); });
        if (stopping) return;
        req = *render_request;
      }
      const auto t0 = Clock::now();
      const std::uint64_t version = casting_version;
      camera->set_slide_position_mm(req.first);
      std::lock_guard lock(render_mutex);
      rendered = {req.first, version};
      if (render_request && *render_request == rendered) render_request.reset();
      log->debug("image for slide {} mm (casting version {}) in {:.0f} ms", req.first, version,
                 std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
    }
  }

  // ---- the casting ----

  void set_casting(std::optional<Casting> c, const std::string& what) {
    {
      std::lock_guard lock(casting_mutex);
      casting = std::move(c);
      ++casting_version;
    }
    event(what);
  }

  void load(std::uint64_t seed) { set_casting(Casting::make(world, seed), "part loaded: casting " + std::to_string(seed)); }

  void load_wrong(std::uint64_t seed) {
    // Upside down would be a wrong part too, but the height-field renderer cannot show a part
    // from below.
    const config::PartRecipe mirrored = mirrored_in_x(world);
    set_casting(Casting::make(mirrored, seed), "wrong part loaded: casting " + std::to_string(seed) + " mirrored (the other hand)");
  }

  void unload() {
    {
      std::lock_guard lock(casting_mutex);
      // the camera goes on seeing the last casting's scene, without the part
      if (auto last = std::exchange(casting, std::nullopt)) {
        empty_scene = std::move(last);
        empty_scene->take_off_fixture();
      }
      ++casting_version;
    }
    event("fixture emptied");
  }

  void executed(const Trajectory& t, std::function<void()> done) {
    if (t.points.empty() || !options.grind) return done();
    auto self = shared_from_this();
    asio::post(grinder, [self, t, done = std::move(done)] {
      self->grind_executed(t);
      done();
    });
  }

  /// The recipe region whose ROI holds a part-frame point ("" when none does).
  std::string region_at(const Vec3& x) const {
    for (const auto& r : recipe.regions)
      if (config::roi_contains(r, x)) return r.name;
    return {};
  }

  const config::Tool& tool_for_segment(const std::vector<TrajectoryPoint>& pts, const Transform& T_part_base) const {
    std::map<std::string, int> votes;
    for (const auto& p : pts) {
      const Vec3 x = T_part_base * p.T_base_tool.position_mm;
      for (const auto& r : recipe.regions)
        if (config::roi_contains(r, x, 5.0)) ++votes[r.tool];
    }
    std::string best;
    int n = -1;
    for (const auto& [tool, v] : votes)
      if (v > n) best = tool, n = v;
    if (best.empty() && !recipe.regions.empty()) best = recipe.regions.front().tool;
    return find_tool(recipe, best.empty() ? recipe.tools.front().name : best);
  }

  void grind_executed(const Trajectory& t) {
    const auto t0 = Clock::now();
    std::lock_guard lock(casting_mutex);
    if (!casting) {
      event("robot moved over an empty fixture (" + std::to_string(t.points.size()) + " points)");
      return;
    }
    CellLimits limits;
    const auto& s = options.cell.safety;
    limits.workspace_min_mm = Vec3(s.workspace_min_mm[0], s.workspace_min_mm[1], s.workspace_min_mm[2]);
    limits.workspace_max_mm = Vec3(s.workspace_max_mm[0], s.workspace_max_mm[1], s.workspace_max_mm[2]);
    limits.max_speed_mm_s = s.max_speed_mm_s;
    limits.max_spindle_rpm = s.max_spindle_rpm;
    const Transform T_part_base = casting->T_base_part().inverse();
    double before = 0.0, after = 0.0, gouge = 0.0;
    Vec3 gouge_at = Vec3::Zero();  // part frame
    for (const auto& r : casting->material()) before += r.volume_mm3;
    std::size_t i = 0;
    while (i < t.points.size()) {
      std::size_t j = i;
      while (j < t.points.size() && t.points[j].segment == t.points[i].segment) ++j;
      Trajectory seg;
      seg.part_id = t.part_id;
      seg.points.assign(t.points.begin() + static_cast<std::ptrdiff_t>(i), t.points.begin() + static_cast<std::ptrdiff_t>(j));
      GrindOptions go;
      go.tool = tool_for_segment(seg.points, T_part_base);
      go.noise_seed = casting->seed() * 1000 + casting_version;
      if (drawn) {
        apply_to_grinding(*drawn, go);
        go.tool.diameter_mm = std::max(0.1, go.tool.diameter_mm - 2.0 * worn_mm[go.tool.name]);
      }
      auto r = sim::grind(*casting, seg, go, limits);
      if (r && drawn) worn_mm[go.tool.name] += drawn->wheel_wear_mm_per_cm3(go.tool.name) * r->removed_mm3() / 1000.0;
      if (!r) event("grinding segment " + std::to_string(t.points[i].segment) + " refused: " + r.error().message);
      else
        for (const auto& g : r->gouges)
          if (g.depth_mm > gouge) gouge = g.depth_mm, gouge_at = g.position_mm;
      i = j;
    }
    std::string left;
    for (const auto& r : casting->material()) {
      after += r.volume_mm3;
      char part[120];
      std::snprintf(part, sizeof part, "%s%s %.1f mm3 / %.2f mm", left.empty() ? "" : ", ", r.name.c_str(), r.volume_mm3,
                    r.max_height_mm);
      left += part;
    }
    ++casting_version;
    char buf[200];
    std::snprintf(buf, sizeof buf, "ground %zu points: material %.0f -> %.0f mm3, deepest gouge %.2f mm", t.points.size(),
                  before, after, gouge);
    std::string where;
    if (gouge > 0.0) {
      // where, for whoever reads the cell log: the part-frame point and the region whose ROI holds it
      const std::string region = region_at(gouge_at);
      char at[160];
      std::snprintf(at, sizeof at, " at (%.1f, %.1f, %.1f) in the part frame%s%s", gouge_at.x(), gouge_at.y(), gouge_at.z(),
                    region.empty() ? "" : ", ", region.c_str());
      where = at;
    }
    char took[40];
    std::snprintf(took, sizeof took, " (%.1f s)", std::chrono::duration<double>(Clock::now() - t0).count());
    event(std::string(buf) + where + took + "; left per region (volume / height): " + left);
  }

  // ---- the automatic loop ----

  void supervise() {
    while (!stopping) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
      const auto snap = plc->snapshot();
      if (snap.results.size() > results_seen) {
        for (std::size_t k = results_seen; k < snap.results.size(); ++k) {
          event("result " + std::to_string(k + 1) + ": " + std::string(drivers::plc::name(snap.results[k])));
          // A cycle that ended FAULT did not finish its casting (tool.worn stops one before the
          // scan): it stays on the fixture, and the PLC requests it again once the operator has
          // brought the cell back to Execute (Reset, Unhold).
          if (part_in_progress && snap.results[k] == drivers::plc::CycleResult::fault) stays = true;
          else if (part_in_progress) ++finished;
        }
        results_seen = snap.results.size();
        part_in_progress = false;
      }
      if (!snap.fettle_written || !snap.fettle_valid || !snap.fettle_heartbeat_ok) continue;
      const auto state = snap.fettle.state;
      const auto now = Clock::now();
      if (auto_start && now - last_command_at > std::chrono::seconds(2)) {
        const bool all_done = options.castings > 0 && fed >= options.castings && !part_in_progress && !stays;
        if ((state == packml::State::stopped || (state == packml::State::complete && !all_done))) {
          plc->send_command(packml::Command::reset);
          last_command_at = now;
          event("PLC: Reset");
        } else if (state == packml::State::idle && !all_done) {
          plc->send_command(packml::Command::start);
          last_command_at = now;
          event("PLC: Start");
        }
      }
      // the next casting, or again the one a FAULT left on the fixture once its fault is cleared
      if (options.castings > 0 && !part_in_progress && state == packml::State::execute &&
          snap.parts_requested == snap.cycles_accepted &&
          (stays ? !snap.fettle.fault_latched : fed < options.castings)) {
        const bool again = stays;
        if (!again) load(options.first_seed + static_cast<std::uint64_t>(fed++));
        stays = false;
        plc->part_arrives(recipe_id);
        part_in_progress = true;
        event("cycle request " + std::to_string(fed) + " of " + std::to_string(options.castings) +
              (again ? " again (the casting stayed on the fixture)" : ""));
      }
    }
  }

  Status inject(const std::string& line) {
    std::istringstream in(line);
    std::string dev, what;
    in >> dev;
    std::string rest;
    std::getline(in, rest);
    if (!rest.empty() && rest.front() == ' ') rest.erase(0, 1);
    std::istringstream args(rest);
    args >> what;
    auto bad = [&] { return Error{"sim.cell_command", "'" + line + "': unknown (see fettle-sim cell --help)"}; };
    if (dev == "plc") return plc->apply(rest);
    if (dev == "auto") {
      auto_start = what == "on";
      return {};
    }
    if (dev == "camera") {
      if (!camera) return Error{"sim.cell_command", "no camera in this cell"};
      int n = 1;
      if (what == "drop") {
        args >> n;
        camera->drop_frames(n);
      } else if (what == "stall") {
        args >> n;
        camera->stall_next_frame_ms(n);
      } else if (what == "loss") {
        double r = 0.1;
        args >> n >> r;
        camera->lose_packets(n, r);
      } else {
        return bad();
      }
      return {};
    }
    if (dev == "robot") {
      std::string a, b;
      args >> a >> b;
      // NAK and FAULT codes as docs/robot-protocol.md allows them: UPPER *15(UPPER / DIGIT / "_")
      const std::string& code = what == "nak" ? b : what == "fault-at" ? b : std::string();
      if (!code.empty() && !drivers::robot::is_code(code))
        return Error{"sim.cell_command", "'" + line + "': the code '" + code +
                                             "' is not a protocol code (an upper-case letter, then up to 15 of A-Z 0-9 _)"};
      asio::post(io, [this, what, a, b] {
        auto f = robot->faults();
        if (what == "nak") {
          f.nak_verb = a;
          f.nak_code = b.empty() ? "STATE" : b;
        } else if (what == "disconnect-at-chunk") {
          f.disconnect_at_chunk = std::stoi(a);
        } else if (what == "fault-at") {
          f.fault_at_point = std::stoi(a);
          if (!b.empty()) f.fault_code = b;
        } else if (what == "ignore-pings") {
          f.ignore_pings = a == "on";
        } else if (what == "drop") {
          robot->drop_client();
          return;
        } else if (what == "clear") {
          f = RobotFaults{};
        }
        robot->set_faults(f);
      });
      if (what != "nak" && what != "disconnect-at-chunk" && what != "fault-at" && what != "ignore-pings" &&
          what != "drop" && what != "clear")
        return bad();
      return {};
    }
    if (dev == "spindle") {
      std::string name;
      args >> name;
      auto f = parse_spindle_fault(name);
      if (!f) return f.error();
      drive->inject_fault(*f);
      return {};
    }
    if (dev == "part") {
      std::uint64_t seed = options.first_seed;
      if (what == "load") {
        args >> seed;
        load(seed);
      } else if (what == "wrong") {
        args >> seed;
        load_wrong(seed);
      } else if (what == "empty") {
        unload();
      } else if (what == "request") {
        plc->part_arrives(recipe_id);
      } else {
        return bad();
      }
      return {};
    }
    return bad();
  }
};

CellSim::CellSim(CellSimOptions options) : impl_(std::make_shared<Impl>(std::move(options))) {}
CellSim::~CellSim() { impl_->stop(); }
void CellSim::start() { impl_->start(); }
void CellSim::stop() { impl_->stop(); }
int CellSim::plc_port() const { return impl_->plc->port(); }
int CellSim::robot_port() const { return impl_->robot_port(); }
int CellSim::spindle_port() const { return impl_->socketcand->port(); }
void CellSim::load(std::uint64_t seed) { impl_->load(seed); }
void CellSim::unload() { impl_->unload(); }
void CellSim::load_wrong(std::uint64_t seed) { impl_->load_wrong(seed); }
void CellSim::request() { impl_->plc->part_arrives(impl_->recipe_id); }
std::size_t CellSim::results() const { return impl_->results_seen; }
bool CellSim::done() const {
  return impl_->options.castings > 0 && impl_->finished >= impl_->options.castings;
}
void CellSim::set_auto_start(bool on) { impl_->auto_start = on; }
Status CellSim::inject(const std::string& line) { return impl_->inject(line); }
PlcSimSnapshot CellSim::plc() const { return impl_->plc->snapshot(); }
std::vector<double> CellSim::material_mm3() const {
  std::lock_guard lock(impl_->casting_mutex);
  std::vector<double> out;
  if (impl_->casting)
    for (const auto& r : impl_->casting->material()) out.push_back(r.volume_mm3);
  return out;
}
double CellSim::spindle_rpm() const {
  return impl_->on_io<double>([this] { return impl_->drive->velocity_rpm(); });
}
canopen::DriveState CellSim::spindle_state() const {
  return impl_->on_io<canopen::DriveState>([this] { return impl_->drive->state(); });
}
RobotSimStats CellSim::robot_stats() const {
  return impl_->on_io<RobotSimStats>([this] { return impl_->robot->stats(); });
}
void CellSim::on_event(CellEventHandler handler) {
  std::lock_guard lock(impl_->handler_mutex);
  impl_->handler = std::move(handler);
}

}  // namespace fettle::sim
