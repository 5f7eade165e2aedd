#pragma once
// The whole simulated cell in one process (`fettle-sim cell`, and in-process in tests): the
// simulated PLC (Modbus TCP), 3D camera (GigE Vision on UDP 3956 of `address`), robot
// controller (TCP line protocol) and spindle drive (CANopen, reachable from other processes
// through a socketcand server), sharing one casting on the fixture:
//   - the camera renders the simulator's scanner view of the casting in the fixture when the
//     slide arrives at a photo position (the PLC holds the slide "moving" until the image is ready);
//   - the robot's executed path grinds that casting (tool per segment from the recipe's region
//     ROIs), so a ground part re-scans ground;
//   - castings are loaded one after the other (seeds first_seed, first_seed+1, ...) with a cycle
//     request each; the next one once fettled reported a result. A casting whose cycle ended
//     FAULT stays on the fixture and is requested again once the cell is back in Execute with
//     its fault cleared (the operator's Reset and Unhold: `plc reset`, `plc unhold`).
// Fault injection: inject("plc drop"), inject("camera drop 3"), ... (see inject()).
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/config/errors.hpp"
#include "fettle/core/result.hpp"
#include "fettle/drivers/canopen.hpp"
#include "fettle/sim/plc.hpp"
#include "fettle/sim/robot.hpp"

namespace fettle::sim {

struct CellSimOptions {
  config::CellConfig cell;            ///< ports, slide positions, calibration (camera pose), safety, recipes
  std::string address = "127.0.0.1";  ///< every device listens here (loopback)
  int plc_port = -1;                  ///< -1 = [plc] port of the cell file, 0 = ephemeral
  int robot_port = -1;                ///< -1 = [robot] port, 0 = ephemeral
  int spindle_port = -1;              ///< socketcand; -1 = [spindle] port, 0 = ephemeral
  bool camera = true;                 ///< start the GigE Vision camera (UDP 3956 of `address`)
  unsigned camera_width = 1032;       ///< range map size (the 3.2 MP sensor binned 2x2 by default)
  unsigned camera_height = 772;
  bool noise = true;
  int castings = 5;                   ///< castings to feed automatically (0 = feed by load()/request())
  std::uint64_t first_seed = 1;
  int recipe_id = 0;                  ///< 0 = the first [[cell.recipes]] entry
  bool auto_start = true;             ///< send Reset / Start when fettled is Stopped / Idle / Complete
  double robot_speedup = 10.0;        ///< robot execution speed-up (1 = real time)
  /// false: runs take their (accelerated) time but remove no material, for long soak runs where
  /// the grinding simulation (15-30 s of CPU per casting) would dominate; a verification scan
  /// then sees the casting unground.
  bool grind = true;
  double slide_speed_mm_s = 500.0;
  /// A real cell's errors (docs/simulator.md, "Error budget"): the camera mounted off its
  /// calibration, the robot's path off the commanded one, ...; fettled is not told.
  std::optional<config::ErrorBudget> errors;
  std::uint64_t cell_seed = 1;  ///< draws the cell's errors
};

/// One line per thing that happened, for progress output and tests.
using CellEventHandler = std::function<void(const std::string& line)>;

class CellSim {
 public:
  explicit CellSim(CellSimOptions options);
  ~CellSim();
  CellSim(const CellSim&) = delete;
  CellSim& operator=(const CellSim&) = delete;

  /// Starts every device; throws DeviceError (a port or UDP 3956 taken) / UserError (recipe).
  void start();
  void stop();

  [[nodiscard]] int plc_port() const;
  [[nodiscard]] int robot_port() const;
  [[nodiscard]] int spindle_port() const;

  /// Puts casting `seed` on the fixture (replacing what is there).
  void load(std::uint64_t seed);
  /// Empties the fixture.
  void unload();
  /// Puts casting `seed` mirrored in x on the fixture (the other hand of a left/right pair):
  /// not the part the recipe describes.
  void load_wrong(std::uint64_t seed);
  /// Raises a cycle request for what is on the fixture.
  void request();
  /// Results fettled reported so far.
  [[nodiscard]] std::size_t results() const;
  /// True once every automatic casting got a result other than FAULT.
  [[nodiscard]] bool done() const;
  void set_auto_start(bool on);

  /// Applies one line:
  ///   plc <line of PlcSimulator::apply>   e.g. "plc drop", "plc reset", "plc freeze on"
  ///   camera drop N | camera stall MS | camera loss N RATIO
  ///   robot nak VERB CODE | robot disconnect-at-chunk K | robot fault-at POINT [CODE] | robot drop
  ///   robot ignore-pings on|off | robot clear (disarms every robot fault not yet fired)
  ///   spindle fault overcurrent|overtemperature|heartbeat_loss
  ///   part load SEED | part wrong SEED | part empty | part request
  ///   auto on|off
  Status inject(const std::string& line);

  [[nodiscard]] PlcSimSnapshot plc() const;
  /// Material left per region of the casting on the fixture (mm³), in recipe order.
  [[nodiscard]] std::vector<double> material_mm3() const;
  /// The simulated spindle drive's actual speed.
  [[nodiscard]] double spindle_rpm() const;
  /// The simulated drive's CiA 402 state (fault after its master's heartbeat stopped, say).
  [[nodiscard]] canopen::DriveState spindle_state() const;
  /// A copy of what the simulated robot has seen (runs received, completed, halted and why).
  [[nodiscard]] RobotSimStats robot_stats() const;
  void on_event(CellEventHandler handler);

  struct Impl;

 private:
  std::shared_ptr<Impl> impl_;
};

}  // namespace fettle::sim
