#pragma once
#include <string>
#include <vector>

#include "fettle/core/error.hpp"

namespace fettle::config {

/// One problem found in a configuration file, with where it is.
struct Diagnostic {
  std::string file;
  int line = 0;     ///< 1-based; 0 when the problem is the file as a whole
  int column = 0;   ///< 1-based
  std::string key;  ///< dotted key path, e.g. "plc.port" or "regions[2].type"
  std::string message;

  /// "file:line:column: key 'plc.port': message"
  [[nodiscard]] std::string to_string() const;
};

/// Thrown by the loaders when a file has one or more problems; what() lists them all.
class ConfigError : public UserError {
 public:
  explicit ConfigError(std::vector<Diagnostic> diagnostics);
  [[nodiscard]] const std::vector<Diagnostic>& diagnostics() const { return diagnostics_; }

 private:
  std::vector<Diagnostic> diagnostics_;
};

}  // namespace fettle::config
