#pragma once
// A signed distance to the template built from surface samples (points + outward unit normals,
// part frame), for callers that have a sampled template (a golden scan, the vision stage's
// prepared template) rather than an analytic one.
#include <vector>

#include "fettle/core/geometry.hpp"
#include "fettle/planning/planner.hpp"

namespace fettle::planning {

/// Point-to-plane distance (p − s)·n_s to the nearest sample s (> 0 outside) where p projects
/// onto the sampled surface near s (within two sample spacings); beside an edge, where the
/// tangent plane says nothing, the distance to s with the sign voted by the samples around s
/// (both faces of the edge). Samples are
/// hashed into cells of `cell_mm`; points with no sample within `search_mm` get +search_mm
/// (treated as far outside), so the samples must cover every surface a tool comes near and
/// `search_mm` must exceed the largest tool radius plus the allowance (a ball's gouge check
/// queries its centre). The returned callable shares the index (cheap to copy) and is safe to
/// call concurrently.
SignedDistance sdf_from_samples(std::vector<Vec3> points, std::vector<Vec3> normals, double cell_mm = 4.0,
                                double search_mm = 20.0);

}  // namespace fettle::planning
