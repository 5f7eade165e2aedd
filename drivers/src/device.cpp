// The devices' shared lifecycle (device.hpp).
#include "fettle/drivers/device.hpp"

namespace fettle::drivers {

std::string_view to_string(Lifecycle state) {
  switch (state) {
    case Lifecycle::unconfigured:
      return "unconfigured";
    case Lifecycle::inactive:
      return "inactive";
    case Lifecycle::active:
      return "active";
  }
  return "unknown";
}

}  // namespace fettle::drivers
