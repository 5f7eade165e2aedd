#pragma once
// Helpers shared by the fuzz targets: a reader that turns the fuzzer's bytes into typed
// values (never failing: past the end it yields zeros), and FUZZ_CHECK for invariants
// (a broken invariant aborts, so libFuzzer reports it like a crash and keeps the input).
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <string>
#include <string_view>
#include <system_error>
#include <unistd.h>

namespace fettle::fuzz {

class ByteReader {
 public:
  ByteReader(const std::uint8_t* data, std::size_t size) : data_(data), size_(size) {}

  template <class T>
  T take() {
    T v{};
    const std::size_t n = std::min(sizeof(T), size_ - pos_);
    if (n > 0) std::memcpy(&v, data_ + pos_, n);
    pos_ += n;
    return v;
  }
  bool take_bool() { return (take<std::uint8_t>() & 1U) != 0; }
  /// Up to `n` bytes (fewer at the end).
  std::string_view take_bytes(std::size_t n) {
    n = std::min(n, size_ - pos_);
    std::string_view s(reinterpret_cast<const char*>(data_ + pos_), n);
    pos_ += n;
    return s;
  }
  std::string_view rest() { return take_bytes(size_ - pos_); }
  [[nodiscard]] std::size_t remaining() const { return size_ - pos_; }

 private:
  const std::uint8_t* data_;
  std::size_t size_;
  std::size_t pos_ = 0;
};

[[noreturn]] inline void invariant_failed(const char* what, const char* file, int line) {
  std::fprintf(stderr, "%s:%d: fuzz invariant failed: %s\n", file, line, what);
  std::abort();
}

/// A scratch directory for targets whose code under test reads files (one per process,
/// removed at exit).
inline const std::filesystem::path& scratch_dir() {
  struct Dir {
    std::filesystem::path path;
    Dir() {
      std::error_code ec;
      auto base = std::filesystem::temp_directory_path(ec);
      if (ec) base = "/tmp";
      path = base / ("fettle-fuzz-" + std::to_string(::getpid()));
      std::filesystem::create_directories(path, ec);
    }
    ~Dir() {
      std::error_code ec;
      std::filesystem::remove_all(path, ec);
    }
    Dir(const Dir&) = delete;
    Dir& operator=(const Dir&) = delete;
  };
  static const Dir dir;
  return dir.path;
}

/// Writes `bytes` to scratch_dir()/name and returns the path (aborts if it cannot).
inline std::filesystem::path write_scratch(const std::string& name, std::string_view bytes) {
  const auto path = scratch_dir() / name;
  std::FILE* f = std::fopen(path.c_str(), "wb");
  if (f == nullptr) invariant_failed("cannot write the scratch file", __FILE__, __LINE__);
  if (!bytes.empty() && std::fwrite(bytes.data(), 1, bytes.size(), f) != bytes.size())
    invariant_failed("short write to the scratch file", __FILE__, __LINE__);
  std::fclose(f);
  return path;
}

}  // namespace fettle::fuzz

#define FUZZ_CHECK(cond) ((cond) ? static_cast<void>(0) : ::fettle::fuzz::invariant_failed(#cond, __FILE__, __LINE__))
