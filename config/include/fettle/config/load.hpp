#pragma once
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/config/diagnostics.hpp"
#include "fettle/config/part.hpp"
#include "fettle/core/log.hpp"

namespace fettle::config {

/// Reads a cell file; throws ConfigError listing every problem found.
CellConfig load_cell(const std::filesystem::path& file);
/// Reads a part recipe; throws ConfigError listing every problem found.
PartRecipe load_part(const std::filesystem::path& file);

enum class FileKind { automatic, cell, part };

/// Checks a file without throwing: the problems found (empty = valid). With
/// FileKind::automatic a file with a [part] table is a part recipe, else a cell file.
std::vector<Diagnostic> check_file(const std::filesystem::path& file, FileKind kind = FileKind::automatic);

/// Logging options from a cell file's [logging] table; `override_level` is --log-level.
log::Options logging_options(const LoggingSection& logging, std::string program,
                             std::optional<std::string> override_level = std::nullopt);

}  // namespace fettle::config
