#pragma once
// Exit codes shared by fettle, fettled and fettle-sim (documented in docs/exit-codes.md).
namespace fettle::exit_code {
inline constexpr int ok = 0;            ///< success
inline constexpr int failure = 1;       ///< a failure the user can fix (bad file, bad input, check failed)
inline constexpr int usage = 2;         ///< wrong command line
inline constexpr int device = 3;        ///< a device or peer could not be reached or failed
inline constexpr int internal = 4;      ///< a bug: an unexpected exception; please report it
}  // namespace fettle::exit_code
