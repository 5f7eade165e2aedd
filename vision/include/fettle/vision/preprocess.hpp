#pragma once
// Preprocessing: voxel grid (centroid per voxel), pass-through crop, outlier removal, normals.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "fettle/core/cloud.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/vision/cloud.hpp"

namespace fettle::vision {

/// One point per occupied voxel, at the centroid of the voxel's points (normals averaged
/// and renormalised when present). voxel_size > 0, in the cloud's unit.
Cloud voxel_downsample(const Cloud& cloud, double voxel_size);

/// The voxel size for which voxel_downsample keeps about `target_points` points
/// (scale-free: used where the unit of a cloud is unknown).
double voxel_for_count(const Cloud& cloud, std::size_t target_points);

/// Keeps the points inside the box [min, max] given in `frame`, where T_frame_cloud maps
/// the cloud's points into that frame. Returned points stay in the cloud's frame.
Cloud crop_box(const Cloud& cloud, const Transform& T_frame_cloud, const Eigen::Vector3d& min,
               const Eigen::Vector3d& max);

/// Statistical outlier removal: drops points whose mean distance to their k nearest
/// neighbours exceeds mean + std_ratio * stddev over the cloud.
Cloud remove_statistical_outliers(const Cloud& cloud, int k, double std_ratio);

/// Organized variant: neighbours are the valid pixels of a (2r+1)^2 window (no search tree).
OrganizedCloud remove_statistical_outliers(const OrganizedCloud& cloud, int window_radius, double std_ratio);

/// Jump-edge (flying pixel) filter of an organized cloud in its camera frame: a pixel whose
/// range differs from a valid 4-neighbour's by more than `max_jump_mm` is made invalid. Pixels
/// at a depth discontinuity mix the two surfaces and sit in the air between them; the filter
/// also drops the one true pixel on each side of every jump. max_jump_mm <= 0 keeps everything.
OrganizedCloud remove_jump_edges(const OrganizedCloud& cloud, double max_jump_mm);

/// Mixed ("flying") pixels of an organized cloud in its camera frame. A pixel beside a range
/// jump of more than `min_jump_mm` is kept when a straight line through two valid pixels on
/// one side of it (any of the 8 directions, no jump between them) predicts its range within
/// max(`tolerance_mm`, a tenth of its largest jump); otherwise it is mixed: a range between the
/// two surfaces, on no surface. Unlike remove_jump_edges, the true pixels at both sides of a
/// jump stay (the last pixel of a top face fixes its occluding edge). 1 = mixed.
std::vector<std::uint8_t> mixed_pixels(const OrganizedCloud& cloud, double min_jump_mm, double tolerance_mm);

/// Occluding edges of an organized cloud in its camera frame: for each valid, unmixed pixel
/// whose 4-neighbour (or, past one mixed pixel, the next one in that direction) is valid,
/// unmixed and more than `min_jump_mm` farther, the point at the pixel's range on the ray
/// halfway between the two. The face's true edge lies anywhere between those two rays, so the
/// point is on it within half a pixel either way (FineSettings::occluding_edges). `mixed`
/// from mixed_pixels (empty: none).
Cloud occluding_edges(const OrganizedCloud& cloud, const std::vector<std::uint8_t>& mixed, double min_jump_mm);

/// occluding_edges past the pixels mixed_pixels(cloud, min_jump_mm, mixed_tolerance_mm) finds,
/// each pixel's range computed once for both.
Cloud occluding_edges(const OrganizedCloud& cloud, double min_jump_mm, double mixed_tolerance_mm);

/// Normals from the k nearest neighbours (PCA), oriented towards `viewpoint`.
void estimate_normals(Cloud& cloud, int k, const Eigen::Vector3f& viewpoint = Eigen::Vector3f::Zero());

/// Normals of an organized cloud from integral images (average 3D gradient); returns the
/// valid points that have a valid normal, normals oriented towards the camera (origin).
Cloud organized_normals(const OrganizedCloud& cloud, float depth_change_factor = 0.02f,
                        float smoothing_size = 10.0f);

}  // namespace fettle::vision
