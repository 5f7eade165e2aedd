#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "fettle/core/atomic_file.hpp"

namespace fs = std::filesystem;

namespace {
std::string read(const fs::path& p) {
  std::ifstream in(p);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}
}  // namespace

TEST(AtomicFile, WritesAndReplacesLeavingNoTemporaries) {
  const fs::path dir = fs::temp_directory_path() / ("fettle-atomic-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const fs::path f = dir / "report.json";
  ASSERT_TRUE(fettle::write_file_atomic(f, "first").ok());
  EXPECT_EQ(read(f), "first");
  ASSERT_TRUE(fettle::write_file_atomic(f, "second, longer").ok());
  EXPECT_EQ(read(f), "second, longer");
  std::size_t entries = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir)) ++entries;
  EXPECT_EQ(entries, 1U);
  fs::remove_all(dir);
}

TEST(AtomicFile, MissingDirectoryIsAnErrorNamingThePath) {
  const auto s = fettle::write_file_atomic("/nonexistent-fettle-dir/x.json", "data");
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message.find("/nonexistent-fettle-dir"), std::string::npos) << s.error().message;
}
