// Names of ErrorKind (result.hpp), for logs and tests.
#include "fettle/core/result.hpp"

namespace fettle {

std::string_view to_string(ErrorKind kind) {
  switch (kind) {
    case ErrorKind::unspecified: return "unspecified";
    case ErrorKind::config: return "config";
    case ErrorKind::unavailable: return "unavailable";
    case ErrorKind::timeout: return "timeout";
    case ErrorKind::no_data: return "no_data";
    case ErrorKind::refused: return "refused";
    case ErrorKind::device_fault: return "device_fault";
    case ErrorKind::link_lost: return "link_lost";
    case ErrorKind::cancelled: return "cancelled";
    case ErrorKind::invalid_request: return "invalid_request";
    case ErrorKind::no_part: return "no_part";
    case ErrorKind::wrong_part: return "wrong_part";
    case ErrorKind::unplannable: return "unplannable";
    case ErrorKind::internal: return "internal";
  }
  return "?";
}

}  // namespace fettle
