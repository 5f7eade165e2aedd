// fettle: the operator's and integrator's command-line tool. Its commands live in
// daemon/cli/*_command.cpp and register themselves.
#include "fettle/cli/cli.hpp"

int main(int argc, char** argv) {
  return fettle::cli::main_with_commands(
      "fettle", "fettle - tools for a Fettle fettling cell (configuration, inspection, calibration, status)",
      FETTLE_VERSION, argc, argv);
}
