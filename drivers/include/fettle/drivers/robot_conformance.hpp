#pragma once
// Conformance of a robot controller program to docs/robot-protocol.md, checked from outside
// over TCP: each rule opens its own connection, sends what the rule is about and compares the
// robot's answer with what the document says. `fettle robot conformance --address HOST:PORT`
// runs it against an integrator's controller program; tests run it against `fettle-sim robot`
// (test RobotConformance.*).
//
// Rules that make the robot move (an upload that is RUN) run only with `motion`: point the
// robot program at the vendor's offline simulator or keep the robot in a safe mode for them.
#include <functional>
#include <string>
#include <vector>

#include "fettle/core/geometry.hpp"

namespace fettle::drivers::robot {

struct ConformanceOptions {
  std::string address = "127.0.0.1";
  int port = 30100;
  std::string cell_id = "conformance";  ///< sent in HELLO: the cell id the robot program expects
  int reply_timeout_ms = 2000;          ///< per expected line (and for a close)
  bool motion = false;                  ///< also the rules that RUN a short trajectory
  /// Where the rules' trajectories lie (base frame): a point inside the robot's envelope. The
  /// trajectory goes from here 10 mm along +x, tool pointing down (q = 0 1 0 0).
  Vec3 point_mm{300.0, 0.0, 300.0};
  double speed_mm_s = 20.0;
};

struct ConformanceRule {
  enum class Outcome { pass, fail, skipped };
  std::string id;       ///< e.g. "seq.skip"
  std::string section;  ///< of docs/robot-protocol.md, e.g. "2.1"
  std::string rule;     ///< what the robot must do
  Outcome outcome = Outcome::fail;
  std::string detail;   ///< what was seen (fail) or why it did not run (skipped)
};

std::string_view name(ConformanceRule::Outcome o);  ///< "PASS", "FAIL", "SKIP"

/// Runs every rule in order; `on_rule` (if set) is called after each, as a progress report.
/// A robot that cannot be reached fails every rule with the connect error.
std::vector<ConformanceRule> run_conformance(const ConformanceOptions& options,
                                             const std::function<void(const ConformanceRule&)>& on_rule = {});

}  // namespace fettle::drivers::robot
