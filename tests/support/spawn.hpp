#pragma once
// Test helper: starts a program with its stdout on a pipe the test reads (fettle-sim's
// "listening on ..." line, say), so the test can stop it with a signal and reap it.
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <string>
#include <vector>

namespace fettle::test {

struct Spawned {
  pid_t pid = -1;
  FILE* out = nullptr;  ///< the program's stdout
};

/// fork + execv(args[0], args); stderr stays the test's.
inline Spawned spawn(const std::vector<std::string>& args) {
  int fds[2];
  if (::pipe(fds) != 0) return {};
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::dup2(fds[1], 1);
    ::close(fds[0]);
    ::close(fds[1]);
    std::vector<char*> argv;
    for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  ::close(fds[1]);
  return {pid, ::fdopen(fds[0], "r")};
}

}  // namespace fettle::test
