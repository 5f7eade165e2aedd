#pragma once
// Test helper: runs a program as a user does - a child process with piped stdin and stdout
// (fettle-sim's "listening ..." line, commands on its stdin), stopped with SIGTERM (SIGKILL after
// 1 s) and reaped; and run_capture() for a command run to its end.
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <optional>
#include <regex>
#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace fettle::test {

class Child {
 public:
  explicit Child(const std::vector<std::string>& argv) {
    int in[2];
    int out[2];
    if (::pipe(in) != 0 || ::pipe(out) != 0) return;
    pid_ = ::fork();
    if (pid_ == 0) {
      ::dup2(in[0], STDIN_FILENO);
      ::dup2(out[1], STDOUT_FILENO);
      ::close(in[1]);
      ::close(out[0]);
      std::vector<char*> args;
      for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
      args.push_back(nullptr);
      ::execv(args[0], args.data());
      ::_exit(127);
    }
    ::close(in[0]);
    ::close(out[1]);
    to_child_ = in[1];
    from_child_ = out[0];
  }
  ~Child() { kill(); }
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;

  /// The next line of output matching `re` (skipping others), or nothing after `timeout`.
  std::optional<std::smatch> wait_line(const std::regex& re, std::chrono::milliseconds timeout,
                                       std::string* line_out = nullptr) {
    const auto end = std::chrono::steady_clock::now() + timeout;
    while (true) {
      for (auto nl = buffer_.find('\n'); nl != std::string::npos; nl = buffer_.find('\n')) {
        line_ = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        seen_ += line_ + "\n";
        std::smatch m;
        if (std::regex_search(line_, m, re)) {
          if (line_out != nullptr) *line_out = line_;
          return m;
        }
      }
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(end - std::chrono::steady_clock::now());
      if (left.count() <= 0 || !read_some(static_cast<int>(left.count()))) return std::nullopt;
    }
  }

  void write_line(const std::string& s) {
    const std::string l = s + "\n";
    ASSERT_EQ(::write(to_child_, l.data(), l.size()), static_cast<ssize_t>(l.size()));
  }

  /// SIGTERM, then SIGKILL if it has not exited within 1 s; returns its wait status (-1 when
  /// it was not running). What it wrote stays readable with rest().
  int stop() {
    int status = -1;
    if (pid_ <= 0) return status;
    ::kill(pid_, SIGTERM);
    for (int i = 0; i < 100; ++i) {
      if (::waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return status;
      }
      ::usleep(10000);
    }
    ::kill(pid_, SIGKILL);
    ::waitpid(pid_, &status, 0);
    pid_ = -1;
    return status;
  }

  /// Its output not yet read by wait_line(), up to the end (after stop(): all of it).
  std::string rest() {
    while (read_some(1000)) {
    }
    std::string out;
    out.swap(buffer_);
    seen_ += out;
    return out;
  }

  void kill() {
    (void)stop();
    if (to_child_ >= 0) ::close(to_child_);
    if (from_child_ >= 0) ::close(from_child_);
    to_child_ = from_child_ = -1;
  }

  [[nodiscard]] bool started() const { return pid_ > 0; }
  [[nodiscard]] const std::string& output() const { return seen_; }

 private:
  /// Reads what is there within `timeout_ms` into the buffer; false at end of output or timeout.
  bool read_some(int timeout_ms) {
    if (from_child_ < 0) return false;
    pollfd p{from_child_, POLLIN, 0};
    if (::poll(&p, 1, timeout_ms) <= 0) return false;
    std::array<char, 1024> chunk{};
    const auto n = ::read(from_child_, chunk.data(), chunk.size());
    if (n <= 0) return false;
    buffer_.append(chunk.data(), static_cast<std::size_t>(n));
    return true;
  }

  pid_t pid_ = -1;
  int to_child_ = -1;
  int from_child_ = -1;
  std::string buffer_;
  std::string line_;
  std::string seen_;
};

/// Runs `cmd` with sh to its end; its stdout and stderr, and its exit code (-1 if it did not exit).
inline std::string run_capture(const std::string& cmd, int& exit_code) {
  FILE* pipe = ::popen((cmd + " 2>&1").c_str(), "r");
  if (pipe == nullptr) {
    exit_code = -1;
    return {};
  }
  std::string out;
  std::array<char, 4096> buf{};
  while (std::fgets(buf.data(), buf.size(), pipe) != nullptr) out += buf.data();
  const int status = ::pclose(pipe);
  exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return out;
}

}  // namespace fettle::test
