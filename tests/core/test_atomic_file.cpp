#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

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

// Record files were written 0644 whatever the unit's UMask (issue 40, "also noticed"): a file
// gets 0666 less the process's umask, as a plain create would.
TEST(AtomicFile, TheFileModeFollowsTheUmask) {
  const auto dir = std::filesystem::temp_directory_path() / ("fettle-umask-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const ::mode_t old = ::umask(027);
  ASSERT_TRUE(fettle::write_file_atomic(dir / "a.json", "{}"));
  ::umask(077);
  ASSERT_TRUE(fettle::write_file_atomic(dir / "b.json", "{}"));
  ::umask(old);
  struct stat st {};
  ASSERT_EQ(::stat((dir / "a.json").c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777U, 0640U);
  ASSERT_EQ(::stat((dir / "b.json").c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777U, 0600U);
  std::filesystem::remove_all(dir);
}

