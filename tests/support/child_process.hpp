#pragma once
// Test helper: runs a function in a forked child with a memory cap, and reports how it ended
// and the child's peak RSS, so a test can show that bad input (a header claiming billions of
// points) neither crashes the process nor makes it allocate gigabytes.
//
// The cap is RLIMIT_AS (plain builds). ASan reserves terabytes of address space, so under ASan
// the test must instead run with ASAN_OPTIONS=max_allocation_size_mb=...:allocator_may_return_null=1
// (fettle_add_test ENVIRONMENT); oversize allocations then fail with std::bad_alloc.
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <functional>
#include <new>
#include <string>

#if defined(__SANITIZE_ADDRESS__)
#define FETTLE_TEST_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define FETTLE_TEST_ASAN 1
#endif
#endif

namespace fettle::test {

struct ChildOutcome {
  enum class How { returned, threw, bad_alloc, crashed } how = How::crashed;
  std::string detail;  ///< the signal or exit status, for failure messages
  long max_rss_mb = 0;
};

/// Runs `f` in a child process limited to `limit_mb` of address space (plain builds).
/// returned: f returned; threw: f threw an exception (not bad_alloc); bad_alloc: an
/// allocation failed; crashed: a signal or another exit status.
inline ChildOutcome run_in_child(const std::function<void()>& f, long limit_mb = 2048) {
  const pid_t pid = ::fork();
  if (pid == 0) {
#ifndef FETTLE_TEST_ASAN
    const rlimit lim{static_cast<rlim_t>(limit_mb) << 20, static_cast<rlim_t>(limit_mb) << 20};
    ::setrlimit(RLIMIT_AS, &lim);
#else
    (void)limit_mb;
#endif
    int code = 0;
    try {
      f();
    } catch (const std::bad_alloc&) {
      code = 20;
    } catch (...) {
      code = 10;
    }
    ::_exit(code);
  }
  ChildOutcome out;
  int status = 0;
  rusage usage{};
  if (pid < 0 || ::wait4(pid, &status, 0, &usage) != pid) {
    out.detail = "fork/wait failed";
    return out;
  }
  out.max_rss_mb = usage.ru_maxrss / 1024;
  if (WIFEXITED(status)) {
    const int code = WEXITSTATUS(status);
    out.how = code == 0 ? ChildOutcome::How::returned
              : code == 10 ? ChildOutcome::How::threw
              : code == 20 ? ChildOutcome::How::bad_alloc
                           : ChildOutcome::How::crashed;
    out.detail = "exit status " + std::to_string(code);
  } else if (WIFSIGNALED(status)) {
    out.detail = "signal " + std::to_string(WTERMSIG(status));
  }
  return out;
}

}  // namespace fettle::test
