// What the fettle CLI's status and cycles commands share (see control.hpp).
#include <cstdio>

#include "fettle/config/load.hpp"
#include "fettle/core/error.hpp"
#include "fettle/daemon/control.hpp"

namespace fettle::daemon::control {

std::filesystem::path socket_for_cli(const std::optional<std::filesystem::path>& socket,
                                     const std::optional<std::filesystem::path>& config) {
  if (socket && !socket->empty()) return *socket;
  if (config && !config->empty()) return config::load_cell(*config).control.socket;
  return config::ControlSection{}.socket;
}

json cli_request(const std::filesystem::path& socket, const json& request, std::chrono::milliseconds timeout) {
  auto reply = call(socket, request, timeout);
  if (!reply) {
    if (reply.error().code == code::permission_denied) throw UserError(reply.error().message);
    throw DeviceError(reply.error().message);
  }
  const json& r = reply.value();
  if (!r.value("ok", false)) {
    const std::string message = r.contains("error") && r["error"].is_string() ? r["error"].get<std::string>() : r.dump();
    const std::string c = r.contains("code") && r["code"].is_string() ? r["code"].get<std::string>() : "?";
    throw UserError("fettled refused: " + message + " [" + c + "]");
  }
  return reply.value();
}

std::string display_text(const json& v) {
  if (v.is_null()) return "-";
  if (v.is_string()) return v.get<std::string>();
  if (v.is_boolean()) return v.get<bool>() ? "yes" : "no";
  if (v.is_number_float()) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.3g", v.get<double>());
    return buf;
  }
  return v.dump();
}

}  // namespace fettle::daemon::control
