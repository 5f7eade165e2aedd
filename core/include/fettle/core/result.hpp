#pragma once
// Results as values on the cycle path (exceptions are for setup and misuse).
#include <cstdint>
#include <string>
#include <string_view>
#include <utility>
#include <variant>

namespace fettle {

/// What kind of failure an Error is, for code that must react to it (fettled's fault table,
/// daemon/faults.hpp): set where the failure is known, never parsed back from `code`.
enum class ErrorKind : std::uint8_t {
  unspecified,      ///< nothing to react to beyond the component that failed
  config,           ///< options that cannot work (the message names the key)
  unavailable,      ///< the device is not connected, not ready or cannot be opened
  timeout,          ///< the device did not answer, or did not finish, in time
  no_data,          ///< the device answered without data (a camera without a complete frame)
  refused,          ///< the device refused a valid request (the robot's NAK)
  device_fault,     ///< the device reports a fault of its own (robot FAULT, drive fault)
  link_lost,        ///< the connection broke, or the peer broke the protocol
  cancelled,        ///< stopped on request, or the link was shut down
  invalid_request,  ///< our own request was invalid (a point the robot cannot take)
  no_part,          ///< the scan shows no part in the fixture
  wrong_part,       ///< the scan shows a part that is not the recipe's
  unplannable,      ///< no grinding path for this part keeps the cell's limits
  internal,         ///< an exception where none was expected (a bug)
};
[[nodiscard]] std::string_view to_string(ErrorKind kind);

// GCC 12 reports `kind` as maybe uninitialized when a std::variant holding an Error is moved
// inside a coroutine frame (daemon/src/runtime/cycle_runner.cpp): its analysis does not follow
// the variant's index. The warning names this struct's implicit move constructor.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif
/// A failure that says what went wrong and where, for a person to act on.
struct Error {
  std::string code;     ///< stable machine-readable code, e.g. "vision.too_few_points"
  std::string message;  ///< human-readable: what, where, and what to do
  ErrorKind kind = ErrorKind::unspecified;  ///< for code that reacts to it
};
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

/// Either a value or an Error. A minimal std::expected for C++20.
template <class T>
class [[nodiscard]] Result {
 public:
  Result(T value) : v_(std::move(value)) {}         // NOLINT(google-explicit-constructor)
  Result(Error error) : v_(std::move(error)) {}     // NOLINT(google-explicit-constructor)

  [[nodiscard]] bool ok() const { return v_.index() == 0; }
  explicit operator bool() const { return ok(); }

  T& value() & { return std::get<0>(v_); }
  const T& value() const& { return std::get<0>(v_); }
  T&& value() && { return std::get<0>(std::move(v_)); }
  T* operator->() { return &value(); }
  const T* operator->() const { return &value(); }
  T& operator*() & { return value(); }
  const T& operator*() const& { return value(); }

  [[nodiscard]] const Error& error() const { return std::get<1>(v_); }

 private:
  std::variant<T, Error> v_;
};

/// Result of an operation that has no value.
class [[nodiscard]] Status {
 public:
  Status() = default;
  Status(Error error) : error_(std::move(error)), ok_(false) {}  // NOLINT(google-explicit-constructor)
  [[nodiscard]] bool ok() const { return ok_; }
  explicit operator bool() const { return ok_; }
  [[nodiscard]] const Error& error() const { return error_; }

 private:
  Error error_{};
  bool ok_ = true;
};

}  // namespace fettle
