#pragma once
// Shared helpers for the vision tests: data paths, random poses, pose errors.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "fettle/core/geometry.hpp"
#include "fettle/vision/cloud.hpp"
#include "../support/draws.hpp"

namespace fettle::vision::test {

inline std::filesystem::path data(const std::string& name) { return std::filesystem::path(FETTLE_TEST_DATA_DIR) / name; }

/// A test that writes files into the temp directory (names carry the prefix and the pid) and
/// removes them afterwards.
class TempFilesTest : public ::testing::Test {
 protected:
  explicit TempFilesTest(std::string prefix) : prefix_(std::move(prefix)) {}
  std::filesystem::path path(const std::string& name) {
    const auto p = std::filesystem::temp_directory_path() / (prefix_ + std::to_string(::getpid()) + "-" + name);
    files_.push_back(p);
    return p;
  }
  std::filesystem::path write(const std::string& name, const std::string& bytes) {
    const auto p = path(name);
    std::ofstream(p, std::ios::binary) << bytes;
    return p;
  }
  void TearDown() override {
    for (const auto& f : files_) std::filesystem::remove(f);
  }

 private:
  std::string prefix_;
  std::vector<std::filesystem::path> files_;
};

/// A random rigid transform: rotation angle exactly `angle_rad` about a random axis,
/// translation of length `translation`.
inline Transform random_transform(std::mt19937_64& rng, double angle_rad, double translation) {
  std::normal_distribution<double> g(0.0, 1.0);
  const Vec3 axis = fettle::test::draw3<Vec3>(g, rng).normalized();
  const Vec3 dir = fettle::test::draw3<Vec3>(g, rng).normalized();
  Transform T = Transform::Identity();
  T.linear() = Eigen::AngleAxisd(angle_rad, axis).toRotationMatrix();
  T.translation() = dir * translation;
  return T;
}

/// The square z = 0, |x| and |y| <= half_mm, sampled every 0.5 mm, normals +z (a template's
/// flat face).
inline Cloud flat_square(float half_mm) {
  Cloud c;
  for (float x = -half_mm; x <= half_mm; x += 0.5f)
    for (float y = -half_mm; y <= half_mm; y += 0.5f) {
      c.points.emplace_back(x, y, 0.0f);
      c.normals.emplace_back(Eigen::Vector3f::UnitZ());
    }
  return c;
}

inline Cloud with_noise(const Cloud& c, double sigma, std::mt19937_64& rng) {
  std::normal_distribution<float> g(0.0f, static_cast<float>(sigma));
  Cloud out;
  out.points = c.points;
  for (auto& p : out.points) p += fettle::test::draw3<Eigen::Vector3f>(g, rng);
  return out;
}

struct PoseError {
  double translation;
  double rotation_rad;
};

inline PoseError pose_error(const Transform& estimate, const Transform& truth) {
  const Transform d = truth.inverse() * estimate;
  return {(estimate.translation() - truth.translation()).norm(), rotation_angle_rad(d)};
}

/// Pose error of a region: the displacement of `at` (the region's ROI centre, template
/// frame) between the two poses, and the rotation angle between them. Measured at the region
/// rather than at the part origin so a tiny rotation does not count again as a translation.
inline PoseError pose_error_at(const Transform& estimate, const Transform& truth, const Vec3& at) {
  return {(estimate * at - truth * at).norm(), rotation_angle_rad(truth.inverse() * estimate)};
}

}  // namespace fettle::vision::test
