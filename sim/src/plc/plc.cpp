// The simulated PLC: libmodbus TCP server + a small cell model (slide, parts, commands).
#include "fettle/sim/plc.hpp"

#include <arpa/inet.h>
#include <modbus.h>
#include <netinet/in.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <deque>
#include <map>
#include <functional>
#include <mutex>
#include <optional>
#include <sstream>
#include <thread>
#include <utility>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "../cloexec.hpp"

namespace fettle::sim {

namespace plc = drivers::plc;
using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

namespace {

std::optional<long> parse_int(const std::string& s) {
  try {
    std::size_t used = 0;
    const long v = std::stol(s, &used);
    if (used != s.size()) return std::nullopt;
    return v;
  } catch (const std::exception&) {
    return std::nullopt;
  }
}

std::vector<std::string> words(const std::string& line) {
  std::istringstream in(line);
  std::vector<std::string> w;
  for (std::string s; in >> s;) w.push_back(s);
  return w;
}

}  // namespace

Result<std::vector<PlcScriptStep>> parse_plc_script(const std::string& text) {
  std::vector<PlcScriptStep> steps;
  std::istringstream in(text);
  int n = 0;
  for (std::string line; std::getline(in, line);) {
    ++n;
    if (const auto hash = line.find('#'); hash != std::string::npos) line.erase(hash);
    auto w = words(line);
    if (w.empty()) continue;
    PlcScriptStep step;
    std::size_t first = 0;
    if (w[0] == "at") {
      double t = -1.0;
      try {
        std::size_t used = 0;
        if (w.size() >= 2) t = std::stod(w[1], &used);
        if (used != w[1].size()) t = -1.0;
      } catch (const std::exception&) {
        t = -1.0;
      }
      if (w.size() < 3 || !(t >= 0.0))
        return Error{"sim.plc_script", "line " + std::to_string(n) + ": expected 'at SECONDS COMMAND', got '" + line + "'"};
      step.at_s = t;
      first = 2;
    }
    for (std::size_t i = first; i < w.size(); ++i) step.command += (i > first ? " " : "") + w[i];
    steps.push_back(std::move(step));
  }
  std::stable_sort(steps.begin(), steps.end(), [](const auto& a, const auto& b) { return a.at_s < b.at_s; });
  return steps;
}

struct PlcSimulator::Impl {
  explicit Impl(PlcSimOptions o) : options(std::move(o)), log(log::get("sim.plc")) {
    limits.slide_positions = static_cast<int>(std::max<std::size_t>(1, options.photo_positions_mm.size()));
  }

  PlcSimOptions options;
  plc::Limits limits;
  std::shared_ptr<spdlog::logger> log;

  mutable std::mutex mutex;  // guards everything below except the thread-owned sockets
  bool stop_requested = false;
  bool drop_requested = false;
  int reply_delay_ms = 0;
  bool heartbeat_frozen = false;
  bool slide_faulted = false;
  bool results_unread = false;  // "results-ack off": the PLC stops acknowledging results
  std::map<int, std::uint16_t> forced;
  std::deque<int> parts;
  std::deque<packml::Command> commands;
  std::vector<PlcScriptStep> script;
  Clock::time_point script_start{};
  std::size_t script_next = 0;
  std::vector<std::string> events;
  std::function<bool(int, double)> slide_gate;  // see PlcSimulator::set_slide_gate

  // Model.
  plc::PlcInputs in;
  PlcSimSnapshot snap;
  double slide_mm = 0.0;
  double slide_from_mm = 0.0;
  double slide_to_mm = 0.0;
  Clock::time_point slide_started{};
  bool slide_moving = false;
  int last_slide_toggle = -1;
  int last_result_toggle = -1;
  int last_ack_toggle = -1;
  std::optional<packml::State> last_state;
  std::uint16_t last_fettle_heartbeat = 0;
  Clock::time_point fettle_heartbeat_at{};
  Clock::time_point next_heartbeat{};
  Clock::time_point next_part{};
  bool last_fettle_valid = true;
  std::uint16_t last_fault_code = 0;

  modbus_t* ctx = nullptr;
  modbus_mapping_t* mapping = nullptr;
  int listen_fd = -1;
  int bound_port = 0;
  std::vector<int> clients;
  std::thread thread;

  void note(std::string line) {
    log->info("{}", line);
    events.push_back(std::move(line));
  }

  double position_mm(int p) const {
    if (p <= 0) return options.home_mm;
    return options.photo_positions_mm[static_cast<std::size_t>(p - 1)];
  }

  // --- the cell model (called with the mutex held) ---

  void write_plc_block() {
    auto block = plc::encode_plc_block(in);
    for (const auto& [offset, value] : forced)
      if (offset >= plc::reg::plc_block_start && offset < plc::reg::plc_block_start + plc::reg::plc_block_size)
        block[static_cast<std::size_t>(offset - plc::reg::plc_block_start)] = value;
    for (int i = 0; i < plc::reg::plc_block_size; ++i)
      mapping->tab_registers[plc::reg::plc_block_start + i] = block[static_cast<std::size_t>(i)];
    for (const auto& [offset, value] : forced)
      if (offset >= plc::reg::fettle_block_start) mapping->tab_registers[offset] = value;
  }

  void start_slide(int target, Clock::time_point now) {
    slide_from_mm = slide_mm;
    slide_to_mm = position_mm(target);
    slide_started = now;
    slide_moving = true;
    in.slide_status = plc::SlideStatus::moving;
    in.slide_position = target;
  }

  void read_fettle_block(Clock::time_point now) {
    if (!snap.fettle_written) return;
    const std::span<const std::uint16_t> regs(mapping->tab_registers + plc::reg::fettle_block_start,
                                              plc::reg::fettle_block_size);
    const auto d = plc::decode_fettle_block(regs, limits);
    snap.fettle_valid = d.ok();
    if (!d.ok()) {
      if (last_fettle_valid)
        for (const auto& v : d.violations) note("fettle value out of range: " + plc::describe(v));
      last_fettle_valid = false;
      return;
    }
    last_fettle_valid = true;
    const auto& f = d.value;
    snap.fettle = f;
    if (f.heartbeat != last_fettle_heartbeat) {
      last_fettle_heartbeat = f.heartbeat;
      fettle_heartbeat_at = now;
    }
    if (!last_state || *last_state != f.state) {
      last_state = f.state;
      snap.states.push_back(f.state);
      note("fettle state " + std::string(packml::name(f.state)));
    }
    if (f.slide_command_toggle != last_slide_toggle) {
      if (last_slide_toggle != -1) {
        if (slide_faulted) {
          note("slide command to " + std::to_string(f.slide_target) + " ignored: slide faulted");
        } else {
          note("slide command to " + std::to_string(f.slide_target));
          start_slide(f.slide_target, now);
        }
      }
      last_slide_toggle = f.slide_command_toggle;
      // Taken, even by a faulted slide (whose state says it did not move): Fettle may send the next.
      in.slide_command_ack = last_slide_toggle;
    }
    if (f.result_toggle != last_result_toggle) {
      if (last_result_toggle != -1) {
        snap.results.push_back(f.result);
        note("fettle result " + std::string(plc::name(f.result)));
      }
      last_result_toggle = f.result_toggle;
    }
    // Read: acknowledged, so Fettle may publish the next result.
    if (!results_unread && last_result_toggle != -1) in.result_ack = last_result_toggle;
    if (f.cycle_ack_toggle != last_ack_toggle) {
      if (last_ack_toggle != -1 && f.cycle_ack_toggle == in.cycle_request_toggle) {
        ++snap.cycles_accepted;
        note("fettle accepted the cycle request for recipe " + std::to_string(in.recipe_id));
      }
      last_ack_toggle = f.cycle_ack_toggle;
    }
    if (f.fault_code != last_fault_code) {
      note(f.fault_latched ? "fettle fault " + std::to_string(f.fault_code) + " latched" : "fettle fault cleared");
      last_fault_code = f.fault_code;
    }
  }

  void step(Clock::time_point now) {
    // Script.
    while (script_next < script.size() &&
           now - script_start >= std::chrono::duration<double>(script[script_next].at_s)) {
      const auto line = script[script_next++].command;
      if (const auto st = apply_locked(line); !st.ok()) note("script: " + st.error().message);
    }
    // Heartbeat.
    if (now >= next_heartbeat) {
      if (!heartbeat_frozen) ++in.heartbeat;
      next_heartbeat = now + milliseconds(options.heartbeat_period_ms);
    }
    // Parts at a rate.
    if (options.part_every_ms > 0 && now >= next_part) {
      parts.push_back(options.part_recipe_id);
      next_part = now + milliseconds(options.part_every_ms);
    }
    read_fettle_block(now);
    // A new cycle request once the previous one was acknowledged.
    const bool request_pending = snap.fettle.cycle_ack_toggle != in.cycle_request_toggle;
    if (!parts.empty() && !request_pending) {
      in.recipe_id = parts.front();
      parts.pop_front();
      in.cycle_request_toggle ^= 1;
      ++snap.parts_requested;
      note("part arrived: cycle request for recipe " + std::to_string(in.recipe_id));
    }
    // A new PackML command once the previous one was acknowledged.
    const bool command_pending = snap.fettle.command_ack_toggle != in.command_toggle;
    if (!command_pending && in.command != packml::Command::none && snap.fettle_written && !commands_counted) {
      ++snap.commands_acknowledged;
      commands_counted = true;
    }
    if (!commands.empty() && !command_pending) {
      in.command = commands.front();
      commands.pop_front();
      in.command_toggle ^= 1;
      commands_counted = false;
      note("command " + std::string(packml::name(in.command)) + " sent to fettle");
    }
    // Slide.
    if (slide_faulted) {
      slide_moving = false;
      in.slide_status = plc::SlideStatus::fault;
    } else if (slide_moving) {
      const double dist = std::abs(slide_to_mm - slide_from_mm);
      const double t = std::chrono::duration<double>(now - slide_started).count();
      const double travelled = options.slide_speed_mm_s * t;
      if (travelled >= dist && slide_gate && !slide_gate(in.slide_position, slide_to_mm)) {
        slide_mm = slide_to_mm;  // arrived, but the gate holds "moving" (e.g. the camera image is rendering)
      } else if (travelled >= dist) {
        slide_mm = slide_to_mm;
        slide_moving = false;
        in.slide_status = in.slide_position == 0 ? plc::SlideStatus::at_home : plc::SlideStatus::at_position;
        note("slide " + std::string(plc::name(in.slide_status)) + " " + std::to_string(in.slide_position));
      } else {
        slide_mm = slide_from_mm + std::copysign(travelled, slide_to_mm - slide_from_mm);
      }
    }
    snap.fettle_heartbeat_ok =
        snap.fettle_written && now - fettle_heartbeat_at <= milliseconds(options.fettle_heartbeat_timeout_ms);
    write_plc_block();
  }
  bool commands_counted = true;

  Status apply_locked(const std::string& line) {
    const auto w = words(line);
    if (w.empty()) return {};
    const auto& c = w[0];
    auto bad = [&line](const std::string& why) { return Error{"sim.plc_command", "'" + line + "': " + why}; };
    auto on_off = [&](bool& flag) -> Status {
      if (w.size() != 2 || (w[1] != "on" && w[1] != "off")) return bad("expected 'on' or 'off'");
      flag = w[1] == "on";
      return {};
    };
    static const std::map<std::string, packml::Command> kCommands{
        {"reset", packml::Command::reset}, {"start", packml::Command::start}, {"stop", packml::Command::stop},
        {"hold", packml::Command::hold},   {"unhold", packml::Command::unhold}, {"abort", packml::Command::abort},
        {"clear", packml::Command::clear}};
    if (const auto it = kCommands.find(c); it != kCommands.end() && w.size() == 1) {
      queue_command(it->second);
      return {};
    }
    if (c == "part") {
      const auto id = w.size() == 2 ? parse_int(w[1]) : std::nullopt;
      if (!id || *id < 1 || *id > 65535) return bad("expected 'part RECIPE_ID' with an id from 1 to 65535");
      parts.push_back(static_cast<int>(*id));
      return {};
    }
    if (c == "drop" && w.size() == 1) {
      drop_requested = true;
      return {};
    }
    if (c == "freeze") return on_off(heartbeat_frozen);
    if (c == "results-ack") {
      bool ack = !results_unread;
      if (auto st = on_off(ack); !st.ok()) return st;
      results_unread = !ack;
      return {};
    }
    if (c == "slide-fault") {
      bool f = slide_faulted;
      if (auto st = on_off(f); !st.ok()) return st;
      set_slide_fault(f);
      return {};
    }
    if (c == "force") {
      const auto off = w.size() == 3 ? parse_int(w[1]) : std::nullopt;
      const auto val = w.size() == 3 ? parse_int(w[2]) : std::nullopt;
      if (!off || !val || *off < 0 || *off >= plc::reg::map_size || *val < 0 || *val > 65535)
        return bad("expected 'force OFFSET VALUE' with OFFSET 0 to " + std::to_string(plc::reg::map_size - 1) +
                   " and VALUE 0 to 65535");
      forced[static_cast<int>(*off)] = static_cast<std::uint16_t>(*val);
      return {};
    }
    if (c == "release" && w.size() == 2) {
      if (w[1] == "all") {
        forced.clear();
        return {};
      }
      const auto off = parse_int(w[1]);
      if (!off) return bad("expected 'release OFFSET' or 'release all'");
      forced.erase(static_cast<int>(*off));
      return {};
    }
    if (c == "delay") {
      const auto ms = w.size() == 2 ? parse_int(w[1]) : std::nullopt;
      if (!ms || *ms < 0 || *ms > 60000) return bad("expected 'delay MS' with MS 0 to 60000");
      reply_delay_ms = static_cast<int>(*ms);
      return {};
    }
    return bad("unknown command (part ID, reset, start, stop, hold, unhold, abort, clear, drop, freeze on|off, "
               "slide-fault on|off, results-ack on|off, force OFFSET VALUE, release OFFSET|all, delay MS)");
  }

  void queue_command(packml::Command c) {
    commands.push_back(c);
    if (c == packml::Command::reset && slide_faulted) {
      // A PLC reset also clears the PLC's own slide fault: the slide homes.
      slide_faulted = false;
      start_slide(0, Clock::now());
      note("slide fault reset: homing");
    }
  }

  void set_slide_fault(bool f) {
    if (f && !slide_faulted) note("slide fault injected");
    slide_faulted = f;
    if (!f) in.slide_status = slide_moving ? plc::SlideStatus::moving
                             : in.slide_position == 0 ? plc::SlideStatus::at_home
                                                      : plc::SlideStatus::at_position;
  }

  // --- the server (sim thread) ---

  void close_clients() {
    for (int fd : clients) ::close(fd);
    clients.clear();
  }

  void serve_one(int fd) {
    modbus_set_socket(ctx, fd);
    std::array<std::uint8_t, MODBUS_TCP_MAX_ADU_LENGTH> query{};
    const int rc = modbus_receive(ctx, query.data());
    if (rc == -1) {
      ::close(fd);
      clients.erase(std::find(clients.begin(), clients.end(), fd));
      return;
    }
    if (rc == 0) return;
    int delay = 0;
    {
      std::lock_guard lock(mutex);
      delay = reply_delay_ms;
    }
    if (delay > 0) std::this_thread::sleep_for(milliseconds(delay));
    std::lock_guard lock(mutex);
    step(Clock::now());
    const int header = modbus_get_header_length(ctx);
    const int function = query[static_cast<std::size_t>(header)];
    modbus_reply(ctx, query.data(), rc, mapping);
    ++snap.requests;
    if (function == MODBUS_FC_WRITE_SINGLE_REGISTER || function == MODBUS_FC_WRITE_MULTIPLE_REGISTERS ||
        function == MODBUS_FC_WRITE_AND_READ_REGISTERS) {
      snap.fettle_written = true;
      step(Clock::now());
    }
  }

  void run() {
    log::Scope device{"DEVICE", "sim.plc"};
    while (true) {
      {
        std::lock_guard lock(mutex);
        if (stop_requested) break;
        if (drop_requested) {
          drop_requested = false;
          if (!clients.empty()) note("dropping " + std::to_string(clients.size()) + " connection(s)");
          close_clients();
        }
        step(Clock::now());
        snap.clients = static_cast<int>(clients.size());
      }
      fd_set fds;
      FD_ZERO(&fds);
      FD_SET(listen_fd, &fds);
      int max_fd = listen_fd;
      for (int fd : clients) {
        FD_SET(fd, &fds);
        max_fd = std::max(max_fd, fd);
      }
      timeval tv{0, 5000};
      const int n = ::select(max_fd + 1, &fds, nullptr, nullptr, &tv);
      if (n <= 0) continue;
      if (FD_ISSET(listen_fd, &fds)) {
        const int fd = ::accept4(listen_fd, nullptr, nullptr, SOCK_CLOEXEC);
        if (fd >= 0) clients.push_back(fd);
      }
      const auto ready = clients;
      for (int fd : ready)
        if (FD_ISSET(fd, &fds)) serve_one(fd);
    }
    close_clients();
  }
};

PlcSimulator::PlcSimulator(PlcSimOptions options) : impl_(std::make_unique<Impl>(std::move(options))) {
  auto& o = impl_->options;
  if (o.photo_positions_mm.empty() || o.photo_positions_mm.size() > 16)
    throw UserError("simulated PLC: 1 to 16 photo positions needed, got " + std::to_string(o.photo_positions_mm.size()));
  if (!(o.slide_speed_mm_s > 0.0)) throw UserError("simulated PLC: slide speed must be > 0 mm/s");
  if (o.register_base < 0 || o.register_base > 65535 - plc::reg::map_size)
    throw UserError("simulated PLC: register_base " + std::to_string(o.register_base) + " out of range");
  if (o.heartbeat_period_ms < 1) throw UserError("simulated PLC: heartbeat period must be >= 1 ms");
  impl_->in.slide_status = plc::SlideStatus::at_home;
  impl_->slide_mm = o.home_mm;
}

PlcSimulator::~PlcSimulator() { stop(); }

void PlcSimulator::start() {
  auto& d = *impl_;
  if (d.thread.joinable()) return;
  d.ctx = modbus_new_tcp(d.options.address.c_str(), d.options.port);
  if (d.ctx == nullptr) throw DeviceError("simulated PLC: cannot create a Modbus context: " + std::string(modbus_strerror(errno)));
  d.mapping = modbus_mapping_new_start_address(0, 0, 0, 0, static_cast<unsigned>(d.options.register_base),
                                               static_cast<unsigned>(plc::reg::map_size), 0, 0);
  d.listen_fd = modbus_tcp_listen(d.ctx, 8);
  if (d.listen_fd == -1) {
    const std::string err = modbus_strerror(errno);
    modbus_mapping_free(d.mapping);
    modbus_free(d.ctx);
    d.mapping = nullptr;
    d.ctx = nullptr;
    throw DeviceError("simulated PLC: cannot listen on " + d.options.address + ":" + std::to_string(d.options.port) +
                      ": " + err);
  }
  fettle::sim::detail::set_cloexec(d.listen_fd);  // Debian 12's libmodbus sets it already (tested)
  sockaddr_in addr{};
  socklen_t len = sizeof addr;
  ::getsockname(d.listen_fd, reinterpret_cast<sockaddr*>(&addr), &len);
  d.bound_port = ntohs(addr.sin_port);
  {
    std::lock_guard lock(d.mutex);
    d.stop_requested = false;
    const auto now = Clock::now();
    d.next_heartbeat = now;
    d.next_part = now + milliseconds(d.options.part_every_ms);
    d.fettle_heartbeat_at = now;
    d.write_plc_block();
  }
  d.thread = std::thread([&d] { d.run(); });
}

void PlcSimulator::stop() {
  auto& d = *impl_;
  {
    std::lock_guard lock(d.mutex);
    d.stop_requested = true;
  }
  if (d.thread.joinable()) d.thread.join();
  if (d.listen_fd != -1) ::close(d.listen_fd);
  d.listen_fd = -1;
  if (d.mapping != nullptr) modbus_mapping_free(d.mapping);
  d.mapping = nullptr;
  if (d.ctx != nullptr) modbus_free(d.ctx);  // its socket was one of ours, already closed
  d.ctx = nullptr;
}

int PlcSimulator::port() const { return impl_->bound_port; }

void PlcSimulator::part_arrives(int recipe_id) {
  std::lock_guard lock(impl_->mutex);
  impl_->parts.push_back(recipe_id);
}

void PlcSimulator::send_command(packml::Command command) {
  std::lock_guard lock(impl_->mutex);
  impl_->queue_command(command);
}

void PlcSimulator::run_script(std::vector<PlcScriptStep> steps) {
  std::lock_guard lock(impl_->mutex);
  impl_->script = std::move(steps);
  impl_->script_next = 0;
  impl_->script_start = Clock::now();
}

void PlcSimulator::drop_connections() {
  std::lock_guard lock(impl_->mutex);
  impl_->drop_requested = true;
}

void PlcSimulator::freeze_heartbeat(bool frozen) {
  std::lock_guard lock(impl_->mutex);
  impl_->heartbeat_frozen = frozen;
}

void PlcSimulator::set_slide_gate(std::function<bool(int position, double slide_mm)> gate) {
  std::lock_guard lock(impl_->mutex);
  impl_->slide_gate = std::move(gate);
}

void PlcSimulator::slide_fault(bool faulted) {
  std::lock_guard lock(impl_->mutex);
  impl_->set_slide_fault(faulted);
}

void PlcSimulator::force_register(int offset, std::uint16_t value) {
  std::lock_guard lock(impl_->mutex);
  impl_->forced[offset] = value;
}

void PlcSimulator::release_register(int offset) {
  std::lock_guard lock(impl_->mutex);
  impl_->forced.erase(offset);
}

void PlcSimulator::release_all_registers() {
  std::lock_guard lock(impl_->mutex);
  impl_->forced.clear();
}

void PlcSimulator::set_reply_delay_ms(int delay_ms) {
  std::lock_guard lock(impl_->mutex);
  impl_->reply_delay_ms = delay_ms;
}

Status PlcSimulator::apply(const std::string& line) {
  std::lock_guard lock(impl_->mutex);
  return impl_->apply_locked(line);
}

PlcSimSnapshot PlcSimulator::snapshot() const {
  std::lock_guard lock(impl_->mutex);
  auto s = impl_->snap;
  s.plc = impl_->in;
  s.slide_mm = impl_->slide_mm;
  return s;
}

std::vector<std::uint16_t> PlcSimulator::registers() const {
  std::lock_guard lock(impl_->mutex);
  if (impl_->mapping == nullptr) return {};
  return {impl_->mapping->tab_registers, impl_->mapping->tab_registers + plc::reg::map_size};
}

std::vector<std::string> PlcSimulator::take_log() {
  std::lock_guard lock(impl_->mutex);
  return std::exchange(impl_->events, {});
}

}  // namespace fettle::sim
