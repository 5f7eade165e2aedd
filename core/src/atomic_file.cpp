#include "fettle/core/atomic_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <string>

namespace fettle {
namespace {
Error io_error(const std::filesystem::path& path, const char* what) {
  return Error{"io.write", std::string("cannot ") + what + " '" + path.string() + "': " + std::strerror(errno)};
}

/// The process's umask, read without changing it (umask() can only be read by setting it, which
/// races with other threads): /proc/self/status says it since Linux 4.7. 022 if it cannot tell.
::mode_t current_umask() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line))
    if (line.rfind("Umask:", 0) == 0) return static_cast<::mode_t>(std::stoul(line.substr(6), nullptr, 8));
  return 022;
}
}  // namespace

Status write_file_atomic(const std::filesystem::path& path, std::string_view data) {
  const std::filesystem::path dir = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  std::string tmpl = (dir / ("." + path.filename().string() + ".XXXXXX")).string();
  const int fd = ::mkstemp(tmpl.data());
  if (fd < 0) return io_error(tmpl, "create temporary file");
  const std::filesystem::path tmp = tmpl;

  std::size_t written = 0;
  while (written < data.size()) {
    const ssize_t n = ::write(fd, data.data() + written, data.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      Error e = io_error(tmp, "write");
      ::close(fd);
      ::unlink(tmp.c_str());
      return e;
    }
    written += static_cast<std::size_t>(n);
  }
  // mkstemp makes 0600: the file gets what a plain create would, 0666 less the umask (fettled's
  // unit sets UMask=0027: records 0640; test AtomicFile.TheFileModeFollowsTheUmask)
  if (::fchmod(fd, 0666 & ~current_umask()) != 0 || ::fsync(fd) != 0) {
    Error e = io_error(tmp, "sync");
    ::close(fd);
    ::unlink(tmp.c_str());
    return e;
  }
  ::close(fd);
  if (::rename(tmp.c_str(), path.c_str()) != 0) {
    Error e = io_error(path, "rename into");
    ::unlink(tmp.c_str());
    return e;
  }
  const int dfd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (dfd >= 0) {
    (void)::fsync(dfd);
    ::close(dfd);
  }
  return {};
}

}  // namespace fettle
