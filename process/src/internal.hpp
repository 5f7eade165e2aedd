#pragma once
// Helpers shared by the pipeline's translation units (recipe.cpp, process.cpp, verify.cpp); not
// installed: process/include/ has the library's interface.
#include <chrono>
#include <string>
#include <vector>

#include "fettle/core/result.hpp"
#include "fettle/process/pipeline.hpp"

namespace fettle::process {

using Clock = std::chrono::steady_clock;

inline double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

inline void report(const Progress& progress, std::size_t done, std::size_t total, const std::string& step) {
  if (progress) progress(done, total, step);
}

/// The error of a step of the pipeline, named in the message. A planning step's error that
/// says nothing more is of kind unplannable: no path for this part (fettled's fault 505).
inline Error step_error(const std::string& step, const Error& inner) {
  const bool planning = step == "plan" || step == "validate";
  const ErrorKind kind = inner.kind == ErrorKind::unspecified && planning ? ErrorKind::unplannable : inner.kind;
  return Error{inner.code.empty() ? "pipeline." + step : inner.code, "step " + step + ": " + inner.message, kind};
}

/// The part and its regions located in the views (process.cpp says how).
Result<vision::Inspection> locate(const LoadedRecipe& loaded, const std::vector<View>& views, double jump_edge_mm,
                                  std::vector<StepTiming>& timings, const Progress& progress, std::size_t total);

}  // namespace fettle::process
