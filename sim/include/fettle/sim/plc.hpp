#pragma once
// The simulated PLC: a Modbus TCP server (libmodbus) playing the cell PLC's side of the
// register map in docs/plc-interface.md. Usable in-process (tests, `fettle-sim cell`) and
// as `fettle-sim plc`.
//
// It has a camera slide that takes time to travel, parts that arrive on request, on a
// script or at a rate, reset/stop inputs (PackML commands to Fettle), and fault
// injection: drop the connection, freeze the heartbeat, slide fault, out-of-range
// register values, slow replies.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "fettle/core/result.hpp"
#include "fettle/drivers/packml.hpp"
#include "fettle/drivers/plc_registers.hpp"

namespace fettle::sim {

struct PlcSimOptions {
  std::string address = "127.0.0.1";
  int port = 0;  ///< 0 = ephemeral; see PlcSimulator::port()
  int register_base = 0;
  std::vector<double> photo_positions_mm{0.0, 120.0};  ///< slide positions 1..n
  double home_mm = -100.0;                             ///< slide position 0 (home)
  double slide_speed_mm_s = 500.0;
  int heartbeat_period_ms = 100;            ///< the PLC increments its heartbeat this often
  int fettle_heartbeat_timeout_ms = 1000;   ///< Fettle's heartbeat unchanged longer → "lost"
  int part_every_ms = 0;                    ///< > 0: a part arrives this often
  int part_recipe_id = 1;                   ///< recipe of parts arriving at a rate
};

/// One line of a fault/part script: "[at SECONDS] COMMAND ARGS".
struct PlcScriptStep {
  double at_s = 0.0;
  std::string command;  ///< a line PlcSimulator::apply() accepts
};

/// Parses a script: one step per line, '#' comments, blank lines ignored. Errors name the line.
Result<std::vector<PlcScriptStep>> parse_plc_script(const std::string& text);

/// What the simulated PLC sees and has done.
struct PlcSimSnapshot {
  drivers::plc::PlcInputs plc;  ///< the PLC block as the PLC means it (before forced registers)
  drivers::plc::FettleOutputs fettle;
  bool fettle_written = false;        ///< a client has written the Fettle block
  bool fettle_valid = false;          ///< the Fettle block passed its range checks
  bool fettle_heartbeat_ok = false;   ///< Fettle's heartbeat changed within the timeout
  double slide_mm = 0.0;
  int clients = 0;
  long long requests = 0;
  int parts_requested = 0;  ///< cycle requests raised
  int cycles_accepted = 0;  ///< cycle requests acknowledged by Fettle
  std::vector<drivers::plc::CycleResult> results;
  std::vector<packml::State> states;  ///< every PackML state Fettle wrote, in order (changes only)
  int commands_acknowledged = 0;  ///< PackML commands Fettle acknowledged
};

class PlcSimulator {
 public:
  explicit PlcSimulator(PlcSimOptions options);
  ~PlcSimulator();
  PlcSimulator(const PlcSimulator&) = delete;
  PlcSimulator& operator=(const PlcSimulator&) = delete;

  /// Binds and starts serving on a thread of its own; throws DeviceError if it cannot bind.
  void start();
  void stop();
  /// The bound port (after start()).
  [[nodiscard]] int port() const;

  // Inputs.
  void part_arrives(int recipe_id);          ///< raises a cycle request (queued while one is pending)
  void send_command(packml::Command command);  ///< queued while one is unacknowledged
  void run_script(std::vector<PlcScriptStep> steps);  ///< times count from this call

  // Faults.
  void drop_connections();
  void freeze_heartbeat(bool frozen);
  void slide_fault(bool faulted);  ///< a faulted slide stays so until a PackML Reset is sent
  void force_register(int offset, std::uint16_t value);  ///< overrides a PLC register until released
  void release_register(int offset);
  void release_all_registers();
  void set_reply_delay_ms(int delay_ms);  ///< delay before every reply
  /// Called (with the simulator's lock held: return at once) when the slide reaches a position;
  /// while it returns false the slide stays "moving" there (fettle-sim cell renders the camera
  /// image for the new position first). Empty = no gate.
  void set_slide_gate(std::function<bool(int position, double slide_mm)> gate);

  /// Applies one command line: part ID | reset | stop | start | hold | unhold | abort | clear |
  /// drop | freeze on|off | slide-fault on|off | results-ack on|off | force OFFSET VALUE |
  /// release OFFSET|all | delay MS.
  Status apply(const std::string& line);

  [[nodiscard]] PlcSimSnapshot snapshot() const;
  /// The holding registers from register_base, as a client reads them.
  [[nodiscard]] std::vector<std::uint16_t> registers() const;

  /// Lines describing what happened since the last call ("fettle state Execute", ...).
  std::vector<std::string> take_log();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace fettle::sim
