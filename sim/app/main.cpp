// fettle-sim: the hardware simulator. Its commands live in sim/app/*_command.cpp and
// register themselves (FETTLE_COMMAND).
#include "fettle/cli/cli.hpp"

int main(int argc, char** argv) {
  return fettle::cli::main_with_commands(
      "fettle-sim", "fettle-sim - simulated casting, scanner, grinding and cell devices on the real protocols",
      FETTLE_VERSION, argc, argv);
}
