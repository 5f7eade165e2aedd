#pragma once
// The exception hierarchy (exceptions are for setup and misuse; the cycle path returns values).
#include <stdexcept>

namespace fettle {

/// Root of every exception Fettle throws.
class Exception : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// A problem the user can fix (a bad file, bad input): programs exit with code 1.
class UserError : public Exception {
 public:
  using Exception::Exception;
};

/// A device or peer that cannot be reached or misbehaves at setup: programs exit with code 3.
class DeviceError : public Exception {
 public:
  using Exception::Exception;
};

}  // namespace fettle
