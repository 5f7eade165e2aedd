#pragma once
// A signed distance to the template built from surface samples (points + outward unit normals,
// part frame), for callers that have a sampled template (a golden scan, the vision stage's
// prepared template) rather than an analytic one.
#include <vector>

#include "fettle/core/geometry.hpp"
#include "fettle/planning/planner.hpp"

namespace fettle::planning {

/// Point-to-plane distance (p − s)·n_s to the nearest sample s (> 0 outside) where p projects
/// onto the sampled surface near s (within one sample spacing). At an edge (a sample within two
/// spacings of s whose normal turns more than 45°) both tangent planes count: the larger
/// distance at a convex edge, the smaller at a concave one. Off the sampled patch the distance
/// to s (short by at most a spacing) with that sign. Samples are
/// hashed into cells of `cell_mm`; points with no sample within `search_mm` get +search_mm
/// (treated as far outside), so the samples must cover every surface a tool comes near and
/// `search_mm` must exceed the largest tool radius plus the allowance (a ball's gouge check
/// queries its centre). The returned callable shares the index (cheap to copy) and is safe to
/// call concurrently.
SignedDistance sdf_from_samples(std::vector<Vec3> points, std::vector<Vec3> normals, double cell_mm = 4.0,
                                double search_mm = 20.0);

}  // namespace fettle::planning
