// Runtime's public functions (runtime.hpp); Runtime::Impl is in runtime_impl.hpp.
#include "runtime_impl.hpp"

namespace fettle::daemon {

Runtime::Runtime(asio::io_context& io, config::CellConfig cell, RuntimeOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(cell), std::move(options))) {}

Runtime::~Runtime() {
  if (impl_->plc_link) impl_->plc_link->deactivate();
  impl_->workers.join();
  impl_->camera_thread.join();
  if (impl_->camera) impl_->camera->deactivate();  // its threads are gone: nothing captures any more
  impl_->record_writer.join();
}

void Runtime::start() { impl_->setup(); }
void Runtime::shutdown(std::function<void()> done) { impl_->shutdown(std::move(done)); }
Status Runtime::command(Command c, const std::string& source) { return impl_->command(c, source); }
RuntimeStatus Runtime::status_snapshot() const { return impl_->snapshot(); }
State Runtime::state() const { return impl_->machine.state(); }

json Runtime::status() {
  const auto s = impl_->snapshot();
  json j{{"state", packml::name(s.state)},
         {"state_code", packml::code(s.state)},
         {"cycle_id", s.cycle_id.empty() ? json(nullptr) : json(s.cycle_id)},
         {"step", s.step},
         {"cycles_total", s.cycles_total},
         {"last_result", s.last_result},
         {"uptime_s", ms_since(impl_->started) / 1000.0},
         {"plc_up", s.plc_up},
         {"robot", s.robot_state},
         {"spindle_configured", s.spindle_configured},
         {"records", impl_->records.state_dir().string()},
         {"records_warning", impl_->records.warning().empty() ? json(nullptr) : json(impl_->records.warning())}};
#ifdef FETTLE_VERSION
  j["version"] = FETTLE_VERSION;
#endif
  if (s.fault)
    j["fault"] = {{"code", s.fault->number()}, {"id", s.fault->id()}, {"message", s.fault->describe()}};
  else
    j["fault"] = nullptr;
  return j;
}

Result<json> Runtime::last_cycle() {
  auto l = impl_->records.last();
  if (!l) return json(nullptr);
  return l->to_json();
}

Result<json> Runtime::cycles(std::size_t limit) {
  json a = json::array();
  for (const auto& c : impl_->records.cycles(limit)) a.push_back(c.to_json());
  return a;
}

namespace {
Result<json> command_reply(Runtime& rt, Command c) {
  if (auto st = rt.command(c, "control socket"); !st) return st.error();
  return json{{"state", packml::name(rt.state())}};
}
}  // namespace

Result<json> Runtime::reset() { return command_reply(*this, Command::reset); }
Result<json> Runtime::hold() { return command_reply(*this, Command::hold); }
Result<json> Runtime::unhold() { return command_reply(*this, Command::unhold); }

Result<json> Runtime::dry_cycle() {
  auto& i = *impl_;
  if (i.cycle) return Error{"fettled.busy", "cycle " + i.cycle->summary.id + " is running; try again when it ends"};
  const State s = i.machine.state();
  if (s != State::idle && s != State::stopped && s != State::execute && s != State::held)
    return Error{"fettled.state", "a dry cycle needs Idle, Stopped, Held or Execute without a cycle; the cell is " +
                                      std::string(packml::name(s))};
  i.dry_requested = true;
  i.maybe_start_cycle();
  return json{{"cycle_id", i.cycle ? json(i.cycle->summary.id) : json(nullptr)}};
}

Result<json> Runtime::tool_changed(const std::string& tool) { return impl_->tool_changed(tool); }

Status Runtime::maintenance_changing(bool on) {
  if (on && impl_->cycle && !impl_->cycle->dry)
    return Error{"fettled.busy", "a production cycle is running; enter maintenance mode when it ended"};
  impl_->maintenance = on;
  return {};
}

}  // namespace fettle::daemon
