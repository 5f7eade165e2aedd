#pragma once
#include <filesystem>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/config/diagnostics.hpp"
#include "fettle/config/part.hpp"

namespace fettle::config {

/// Reads a cell file; throws ConfigError listing every problem found.
CellConfig load_cell(const std::filesystem::path& file);
/// Reads a part recipe; throws ConfigError listing every problem found.
PartRecipe load_part(const std::filesystem::path& file);

enum class FileKind { automatic, cell, part };

/// Checks a file without throwing: the problems found (empty = valid). With
/// FileKind::automatic a file with a [part] table is a part recipe, else a cell file.
std::vector<Diagnostic> check_file(const std::filesystem::path& file, FileKind kind = FileKind::automatic);

}  // namespace fettle::config
