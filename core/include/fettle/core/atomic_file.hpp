#pragma once
#include <filesystem>
#include <string_view>

#include "fettle/core/result.hpp"

namespace fettle {

/// Writes `data` to `path` atomically: a temporary file beside it, fsync, rename,
/// fsync of the directory. A reader sees the old file or the new one, never a torn one.
Status write_file_atomic(const std::filesystem::path& path, std::string_view data);

}  // namespace fettle
