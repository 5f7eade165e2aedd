// Fuzz target: the cell-file and part-recipe loader (config/load.hpp). The bytes are the
// file's text; the first byte picks how it is read (automatic, as a cell file, as a part
// recipe). Any text must give either a configuration or diagnostics that name the file,
// never a crash, a hang or another exception.
#include <cstdint>
#include <string>

#include "fettle/config/load.hpp"
#include "fuzz_input.hpp"

namespace config = fettle::config;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  const auto mode = in.take<std::uint8_t>() % 3;
  const auto file = fettle::fuzz::write_scratch("fuzz.toml", in.rest());

  const auto kind = mode == 0 ? config::FileKind::automatic : mode == 1 ? config::FileKind::cell : config::FileKind::part;
  const auto diagnostics = config::check_file(file, kind);
  for (const auto& d : diagnostics) {
    FUZZ_CHECK(!d.file.empty());  // this file, or a recipe file a cell file names
    FUZZ_CHECK(!d.message.empty());
    FUZZ_CHECK(d.line >= 0 && d.column >= 0);
    (void)d.to_string();
  }
  // The throwing loaders agree with check_file.
  try {
    if (mode == 1) (void)config::load_cell(file);
    if (mode == 2) (void)config::load_part(file);
    if (mode != 0) FUZZ_CHECK(diagnostics.empty());
  } catch (const config::ConfigError& e) {
    FUZZ_CHECK(!e.diagnostics().empty());
    FUZZ_CHECK(!diagnostics.empty());
  }
  return 0;
}
