// Prepared clouds, FPFH + RANSAC coarse alignment, point-to-plane ICP.
#include "fettle/vision/registration.hpp"

#include <algorithm>
#include <array>
#include <barrier>
#include <cstdint>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <string_view>

#include <unistd.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <pcl/features/fpfh_omp.h>
#include <pcl/features/normal_3d_omp.h>
#include <pcl/kdtree/impl/kdtree_flann.hpp>
#include <pcl/search/kdtree.h>

#include "detail.hpp"
#include "prepared_impl.hpp"
#include "spatial.hpp"
#include "fettle/core/error.hpp"
#include "fettle/vision/plane.hpp"
#include "fettle/vision/preprocess.hpp"

namespace fettle::vision {

PreparedCloud::PreparedCloud() : impl_(std::make_shared<Impl>()) {}
PreparedCloud::PreparedCloud(std::shared_ptr<const Impl> impl) : impl_(std::move(impl)) {}
const Cloud& PreparedCloud::fine() const { return impl_->fine; }
const Cloud& PreparedCloud::coarse() const { return impl_->coarse; }
const PrepareSettings& PreparedCloud::settings() const { return impl_->settings; }
bool PreparedCloud::empty() const { return impl_->fine.empty(); }
double PreparedCloud::fine_spacing() const { return impl_->fine_spacing; }

namespace {

/// Threads for PCL's OpenMP estimators. One in ThreadSanitizer builds (FETTLE_TSAN, from
/// fettle::options): libgomp is not instrumented, so TSan cannot see that its fork and barriers
/// order the workers after the thread that built the search tree, and reports races that are
/// not there. Fettle's own threads (detail::parallel_for, the daemon's pool) are std::threads
/// and stay checked.
unsigned omp_threads(int threads) {
#ifdef FETTLE_TSAN
  (void)threads;
  return 1U;
#else
  return static_cast<unsigned>(threads);
#endif
}

/// Normals of the coarse cloud over a radius, oriented like the (averaged) fine normals.
void coarse_normals(Cloud& coarse, double radius, int threads) {
  const auto pc = detail::to_pcl(coarse.points);
  pcl::NormalEstimationOMP<pcl::PointXYZ, pcl::Normal> ne(omp_threads(threads));
  ne.setInputCloud(pc);
  ne.setSearchMethod(std::make_shared<pcl::search::KdTree<pcl::PointXYZ>>(false));
  ne.setRadiusSearch(radius);
  pcl::PointCloud<pcl::Normal> normals;
  ne.compute(normals);
  for (std::size_t i = 0; i < coarse.size(); ++i) {
    Eigen::Vector3f n = normals[i].getNormalVector3fMap();
    if (!n.allFinite() || n.norm() < 0.5f) continue;  // keep the averaged fine normal
    n.normalize();
    if (n.dot(coarse.normals[i]) < 0.0f) n = -n;
    coarse.normals[i] = n;
  }
}

}  // namespace

PreparedCloud PreparedCloud::prepare(const Cloud& fine, const PrepareSettings& settings) {
  auto impl = std::make_shared<Impl>();
  impl->settings = settings;
  const int threads = detail::thread_count(settings.threads);
  impl->fine = fine;
  if (!impl->fine.has_normals()) estimate_normals(impl->fine, settings.fine_normal_neighbours);
  if (!settings.features) {
    impl->build_trees();
    return PreparedCloud(std::move(impl));
  }
  impl->coarse = voxel_downsample(impl->fine, settings.coarse_voxel);
  const double normal_radius = settings.normal_radius > 0 ? settings.normal_radius : 2.0 * settings.coarse_voxel;
  if (impl->coarse.size() >= 3) coarse_normals(impl->coarse, normal_radius, threads);

  if (impl->coarse.size() >= 5) {
    const auto pc = detail::to_pcl(impl->coarse.points);
    auto normals = std::make_shared<pcl::PointCloud<pcl::Normal>>();
    normals->resize(impl->coarse.size());
    for (std::size_t i = 0; i < impl->coarse.size(); ++i) (*normals)[i].getNormalVector3fMap() = impl->coarse.normals[i];
    pcl::FPFHEstimationOMP<pcl::PointXYZ, pcl::Normal, Feature> fe(omp_threads(threads));
    fe.setInputCloud(pc);
    fe.setInputNormals(normals);
    fe.setSearchMethod(std::make_shared<pcl::search::KdTree<pcl::PointXYZ>>(false));
    fe.setRadiusSearch(settings.feature_radius);
    pcl::PointCloud<Feature> features;
    fe.compute(features);
    // Keep only points with a valid feature (enough neighbours in the support radius).
    Cloud kept;
    for (std::size_t i = 0; i < features.size(); ++i) {
      const auto& h = features[i].histogram;
      if (!std::all_of(std::begin(h), std::end(h), [](float v) { return std::isfinite(v); })) continue;
      kept.points.push_back(impl->coarse.points[i]);
      kept.normals.push_back(impl->coarse.normals[i]);
      impl->features->push_back(features[i]);
    }
    impl->coarse = std::move(kept);
  } else {
    // Fewer than 5 points carry no FPFH feature: no coarse points either, so that every coarse
    // point has its feature (coarse_align reads them by index; test
    // Locate.ATemplateOfTenPointsIsRefusedNotACrash).
    impl->coarse = Cloud{};
  }
  impl->build_trees();
  return PreparedCloud(std::move(impl));
}

namespace {

constexpr std::array<char, 8> kMagic{'F', 'V', 'P', 'R', 'E', 'P', '0', '3'};  // 03: the key after it

template <class T>
void put(std::ofstream& out, const T& v) {
  out.write(reinterpret_cast<const char*>(&v), sizeof(T));
}
template <class T>
bool get(std::ifstream& in, T& v) {
  return static_cast<bool>(in.read(reinterpret_cast<char*>(&v), sizeof(T)));
}
void put_points(std::ofstream& out, const std::vector<Eigen::Vector3f>& v) {
  put(out, static_cast<std::uint64_t>(v.size()));
  out.write(reinterpret_cast<const char*>(v.data()), static_cast<std::streamsize>(v.size() * sizeof(Eigen::Vector3f)));
}
bool get_points(std::ifstream& in, std::vector<Eigen::Vector3f>& v) {
  std::uint64_t n = 0;
  if (!get(in, n) || n > (1ULL << 32)) return false;
  v.resize(n);
  return static_cast<bool>(in.read(reinterpret_cast<char*>(v.data()), static_cast<std::streamsize>(n * sizeof(Eigen::Vector3f))));
}

}  // namespace

void PreparedCloud::save(const std::filesystem::path& file, std::string_view key) const {
  // a name of this process's own: two processes filling the same cache never share a file
  const std::filesystem::path tmp = file.string() + ".tmp-" + std::to_string(::getpid());
  std::error_code ec;
  {
    std::ofstream out(tmp, std::ios::binary);
    if (!out) throw UserError(file.string() + ": cannot write the template cache");
    out.write(kMagic.data(), kMagic.size());
    put(out, static_cast<std::uint64_t>(key.size()));
    out.write(key.data(), static_cast<std::streamsize>(key.size()));
    put(out, impl_->settings);
    put_points(out, impl_->fine.points);
    put_points(out, impl_->fine.normals);
    put_points(out, impl_->coarse.points);
    put_points(out, impl_->coarse.normals);
    put(out, static_cast<std::uint64_t>(impl_->features->size()));
    out.write(reinterpret_cast<const char*>(impl_->features->data()),
              static_cast<std::streamsize>(impl_->features->size() * sizeof(Feature)));
    if (!out) {
      out.close();
      std::filesystem::remove(tmp, ec);
      throw UserError(file.string() + ": writing the template cache failed");
    }
  }
  std::filesystem::rename(tmp, file, ec);
  if (ec) {
    const std::string why = ec.message();
    std::filesystem::remove(tmp, ec);
    throw UserError(file.string() + ": cannot replace the template cache: " + why);
  }
}

std::optional<PreparedCloud> PreparedCloud::load(const std::filesystem::path& file, std::string_view key) {
  std::ifstream in(file, std::ios::binary);
  if (!in) return std::nullopt;
  std::array<char, 8> magic{};
  if (!in.read(magic.data(), magic.size()) || magic != kMagic) return std::nullopt;
  std::uint64_t key_size = 0;
  if (!get(in, key_size) || key_size != key.size()) return std::nullopt;
  std::string stored(key.size(), '\0');
  if (!in.read(stored.data(), static_cast<std::streamsize>(stored.size())) || stored != key) return std::nullopt;
  auto impl = std::make_shared<Impl>();
  std::uint64_t nf = 0;
  if (!get(in, impl->settings) || !get_points(in, impl->fine.points) || !get_points(in, impl->fine.normals) ||
      !get_points(in, impl->coarse.points) || !get_points(in, impl->coarse.normals) || !get(in, nf) ||
      nf != impl->coarse.size())
    return std::nullopt;
  impl->features->resize(nf);
  if (!in.read(reinterpret_cast<char*>(impl->features->data()), static_cast<std::streamsize>(nf * sizeof(Feature))))
    return std::nullopt;
  impl->build_trees();
  return PreparedCloud(std::move(impl));
}

namespace {

/// Which template points the reported fitness counts (FineSettings::viewpoint, covered_mm).
struct Visibility {
  std::optional<Eigen::Vector3f> viewpoint;
  double max_view_angle_deg = 90.0;
  double covered_mm = 0.0;
};

/// Fitness and RMSE on every `stride`-th template point (the scene is bucketed in a grid of
/// cell `distance`: no search tree to build per call), over the points `vis` says a camera
/// could have seen.
Registration evaluate_strided(const Cloud& templ, const Cloud& scene, const Transform& T_scene_template, double distance,
                              std::size_t stride, const Visibility& vis = {}) {
  Registration r;
  r.T_scene_template = T_scene_template;
  if (templ.empty() || scene.empty() || !(distance > 0)) return r;
  const detail::PointGrid grid(scene.points, distance);
  const Eigen::Matrix3f R = T_scene_template.rotation().cast<float>();
  const Eigen::Vector3f t = T_scene_template.translation().cast<float>();
  const auto d2max = static_cast<float>(distance * distance);
  const bool normals = templ.has_normals();
  const bool facing = normals && vis.viewpoint.has_value();
  const auto cos_view = static_cast<float>(std::cos(deg_to_rad(vis.max_view_angle_deg)));
  const bool probe = normals && vis.covered_mm > distance;
  Bounds box = probe ? bounds(scene) : Bounds{};
  box.min.array() -= static_cast<float>(distance);
  box.max.array() += static_cast<float>(distance);
  const auto step = static_cast<float>(distance);
  const auto reach = static_cast<float>(vis.covered_mm);
  const auto in_box = [&](const Eigen::Vector3f& p) {
    return (p.array() >= box.min.array()).all() && (p.array() <= box.max.array()).all();
  };
  const int threads = detail::thread_count(0);
  std::vector<std::size_t> counts(static_cast<std::size_t>(threads), 0);
  std::vector<std::size_t> away(static_cast<std::size_t>(threads), 0);
  std::vector<std::size_t> covered(static_cast<std::size_t>(threads), 0);
  std::vector<double> sums(static_cast<std::size_t>(threads), 0.0);
  stride = std::max<std::size_t>(1, stride);
  const std::size_t n = (templ.size() + stride - 1) / stride;
  detail::parallel_for(n, threads, [&](std::size_t th, std::size_t b, std::size_t e) {
    for (std::size_t k = b; k < e; ++k) {
      const Eigen::Vector3f q = R * templ.points[k * stride] + t;
      const Eigen::Vector3f nq = normals ? Eigen::Vector3f(R * templ.normals[k * stride]) : Eigen::Vector3f::Zero();
      if (facing && nq.dot((*vis.viewpoint - q).normalized()) < cos_view) {
        ++away[th];
        continue;
      }
      const auto [j, d2] = grid.nearest(q, d2max);
      if (j >= 0) {
        ++counts[th];
        sums[th] += d2;
        continue;
      }
      if (!probe) continue;
      for (float s = step; s <= reach; s += step) {
        const Eigen::Vector3f p = q + s * nq;
        if (!in_box(p)) break;
        if (grid.nearest(p, d2max).first >= 0) {
          ++covered[th];
          break;
        }
      }
    }
  });
  std::size_t n_away = 0, n_covered = 0;
  for (std::size_t th = 0; th < counts.size(); ++th) {
    r.inliers += counts[th];
    r.rmse += sums[th];
    n_away += away[th];
    n_covered += covered[th];
  }
  const std::size_t seen = n - n_away;
  r.hidden = n_away + std::min(n_covered, seen / 2);
  r.fitness = n > r.hidden ? static_cast<double>(r.inliers) / static_cast<double>(n - r.hidden) : 0.0;
  r.rmse = r.inliers > 0 ? std::sqrt(r.rmse / static_cast<double>(r.inliers)) : 0.0;
  return r;
}

}  // namespace

Registration evaluate(const Cloud& templ, const Cloud& scene, const Transform& T_scene_template, double distance) {
  return evaluate_strided(templ, scene, T_scene_template, distance, 1);
}

Result<Registration> coarse_align(const PreparedCloud& templ, const PreparedCloud& scene, const CoarseSettings& settings) {
  const auto& T = templ.impl();
  const auto& S = scene.impl();
  if (T.features->size() != T.coarse.size() || S.features->size() != S.coarse.size())
    return Error{"vision.too_few_points", "coarse alignment needs a feature for every coarse point (template " +
                                              std::to_string(T.features->size()) + " of " + std::to_string(T.coarse.size()) +
                                              ", scene " + std::to_string(S.features->size()) + " of " +
                                              std::to_string(S.coarse.size()) + ")"};
  if (T.coarse.size() < 3 || S.coarse.size() < 3)
    return Error{"vision.too_few_points", "coarse alignment needs at least 3 points with features in the template (has " +
                                              std::to_string(T.coarse.size()) + ") and the scene (has " +
                                              std::to_string(S.coarse.size()) + ")"};
  // Correspondences: each template feature to its nearest scene feature; with a pose prior
  // only among the scene points the template point can reach within the prior's tolerance
  // (fewer false matches, and no search through every scene feature).
  const std::size_t n = T.coarse.size();
  std::vector<int> corr(n, -1);
  const int threads = detail::thread_count(settings.threads);
  if (settings.prior) {
    Eigen::Vector3f c = Eigen::Vector3f::Zero();
    for (const auto& p : T.coarse.points) c += p;
    c /= static_cast<float>(n);
    float radius = 0.0f;
    for (const auto& p : T.coarse.points) radius = std::max(radius, (p - c).norm());
    const double reach = settings.prior->position_tolerance +
                         2.0 * std::sin(std::min(settings.prior->rotation_tolerance_rad, 3.0) / 2.0) * radius +
                         2.0 * T.settings.coarse_voxel;
    const detail::PointGrid grid(S.coarse.points, reach);
    const auto reach2 = static_cast<float>(reach * reach);
    const Eigen::Matrix3f R = settings.prior->T_scene_template.rotation().cast<float>();
    const Eigen::Vector3f t = settings.prior->T_scene_template.translation().cast<float>();
    detail::parallel_for(n, threads, [&](std::size_t, std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) {
        const Eigen::Map<const Eigen::Matrix<float, 33, 1>> fi((*T.features)[i].histogram);
        float best = std::numeric_limits<float>::max();
        grid.for_each_within(R * T.coarse.points[i] + t, reach2, [&](std::uint32_t j, float) {
          const Eigen::Map<const Eigen::Matrix<float, 33, 1>> fj((*S.features)[j].histogram);
          const float d = (fi - fj).squaredNorm();
          if (d < best) {
            best = d;
            corr[i] = static_cast<int>(j);
          }
        });
      }
    });
  } else {
    detail::parallel_for(n, threads, [&](std::size_t, std::size_t b, std::size_t e) {
      pcl::Indices idx(1);
      std::vector<float> d2(1);
      for (std::size_t i = b; i < e; ++i)
        if (S.feature_tree->nearestKSearch((*T.features)[i], 1, idx, d2) == 1) corr[i] = idx[0];
    });
  }
  std::vector<std::pair<Eigen::Vector3f, Eigen::Vector3f>> pairs;  // (template, scene)
  pairs.reserve(n);
  for (std::size_t i = 0; i < n; ++i)
    if (corr[i] >= 0) pairs.emplace_back(T.coarse.points[i], S.coarse.points[static_cast<std::size_t>(corr[i])]);
  if (pairs.size() < 3) return Error{"vision.no_match", "fewer than 3 feature correspondences between template and scene", ErrorKind::wrong_part};

  const double voxel = T.settings.coarse_voxel;
  const double inlier = settings.inlier_distance > 0 ? settings.inlier_distance : 1.5 * voxel;
  const auto inlier2 = static_cast<float>(inlier * inlier);
  const auto min_edge = static_cast<float>(2.0 * voxel);
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  for (const auto& p : T.coarse.points) centroid += p.cast<double>();
  centroid /= static_cast<double>(T.coarse.size());

  // Hypotheses are drawn from a counter-based generator keyed on (seed, iteration) and evaluated in
  // fixed blocks; the adaptive iteration limit (Eq. 10) is applied only between blocks and ties go
  // to the lowest iteration. The result therefore depends on the seed alone, not on the number of
  // threads or on how they were scheduled.
  struct Best {
    std::size_t count = 0;
    std::int64_t iteration = std::numeric_limits<std::int64_t>::max();
    Eigen::Matrix4f M = Eigen::Matrix4f::Identity();
  };
  const auto better = [](const Best& a, const Best& b) {
    return a.count > b.count || (a.count == b.count && a.iteration < b.iteration);
  };
  constexpr std::int64_t kBlock = 256;
  const auto n_threads = static_cast<std::size_t>(threads);
  std::vector<Best> local(n_threads);
  Best top;
  std::int64_t limit = settings.max_iterations;
  std::int64_t block_begin = 0;
  bool finished = limit <= 0;
  std::barrier sync(static_cast<std::ptrdiff_t>(n_threads), [&]() noexcept {
    for (const auto& b : local)
      if (better(b, top)) top = b;
    if (top.count > 0)
      limit = std::min(limit, ransac_iterations(settings.probability,
                                                static_cast<double>(top.count) / static_cast<double>(pairs.size()), 3,
                                                settings.max_iterations));
    block_begin += kBlock;
    finished = block_begin >= limit;
  });
  auto hypothesis = [&](std::int64_t iteration, Best& best) {
    detail::SplitMix64 rng(settings.seed ^ (0x9E3779B97F4A7C15ULL * static_cast<std::uint64_t>(iteration + 1)));
    std::uniform_int_distribution<std::size_t> pick(0, pairs.size() - 1);
    const std::array<std::size_t, 3> s{pick(rng), pick(rng), pick(rng)};
    if (s[0] == s[1] || s[0] == s[2] || s[1] == s[2]) return;
    for (int a = 0; a < 3; ++a) {
      const int b = (a + 1) % 3;
      const float lt = (pairs[s[a]].first - pairs[s[b]].first).norm();
      const float ls = (pairs[s[a]].second - pairs[s[b]].second).norm();
      if (lt < min_edge || ls < min_edge) return;
      if (std::min(lt, ls) / std::max(lt, ls) < settings.edge_similarity) return;
    }
    Eigen::Matrix3d src;  // double: Eigen's umeyama in float trips GCC 12's -Warray-bounds
    Eigen::Matrix3d dst;
    for (int a = 0; a < 3; ++a) {
      src.col(a) = pairs[s[a]].first.cast<double>();
      dst.col(a) = pairs[s[a]].second.cast<double>();
    }
    const Eigen::Matrix4f M = Eigen::umeyama(src, dst, false).cast<float>();
    if (!M.allFinite()) return;
    if (settings.prior) {
      Transform Tm = Transform::Identity();
      Tm.matrix() = M.cast<double>();
      const Transform delta = settings.prior->T_scene_template.inverse() * Tm;
      if (rotation_angle_rad(delta) > settings.prior->rotation_tolerance_rad) return;
      if ((Tm * centroid - settings.prior->T_scene_template * centroid).norm() > settings.prior->position_tolerance) return;
    }
    const Eigen::Matrix3f R = M.topLeftCorner<3, 3>();
    const Eigen::Vector3f t = M.topRightCorner<3, 1>();
    std::size_t count = 0;
    for (const auto& [pt, ps] : pairs) count += (R * pt + t - ps).squaredNorm() <= inlier2 ? 1 : 0;
    const Best candidate{count, iteration, M};
    if (better(candidate, best)) best = candidate;
  };
  auto worker = [&](std::size_t th) {
    while (!finished) {
      const std::int64_t end = std::min(block_begin + kBlock, limit);
      for (std::int64_t i = block_begin + static_cast<std::int64_t>(th); i < end; i += static_cast<std::int64_t>(n_threads))
        hypothesis(i, local[th]);
      sync.arrive_and_wait();
    }
  };
  std::vector<std::thread> pool;
  for (std::size_t th = 1; th < n_threads; ++th) pool.emplace_back(worker, th);
  worker(0);
  for (auto& p : pool) p.join();
  if (top.count < 3)
    return Error{"vision.no_match", settings.prior ? "no feature match within the fixture pose prior"
                                                   : "no consistent feature match between template and scene", ErrorKind::wrong_part};
  // Refit on all inlier correspondences (twice, as the inlier set may grow).
  Eigen::Matrix4f M = top.M;
  for (int pass = 0; pass < 2; ++pass) {
    const Eigen::Matrix3f R = M.topLeftCorner<3, 3>();
    const Eigen::Vector3f t = M.topRightCorner<3, 1>();
    std::vector<std::size_t> in;
    for (std::size_t i = 0; i < pairs.size(); ++i)
      if ((R * pairs[i].first + t - pairs[i].second).squaredNorm() <= inlier2) in.push_back(i);
    if (in.size() < 3) break;
    Eigen::Matrix3Xd src(3, in.size());
    Eigen::Matrix3Xd dst(3, in.size());
    for (std::size_t k = 0; k < in.size(); ++k) {
      src.col(static_cast<Eigen::Index>(k)) = pairs[in[k]].first.cast<double>();
      dst.col(static_cast<Eigen::Index>(k)) = pairs[in[k]].second.cast<double>();
    }
    const Eigen::Matrix4f refit = Eigen::umeyama(src, dst, false).cast<float>();
    if (refit.allFinite()) M = refit;
  }
  Transform Tm = Transform::Identity();
  Tm.matrix() = M.cast<double>();
  Registration r = evaluate(T.coarse, S.coarse, Tm, inlier);
  r.iterations = static_cast<int>(std::min(block_begin, limit));
  r.converged = true;
  return r;
}

namespace {

/// Cells of `size` holding at least one inserted point (detail::CellIndex keys); near(p): a
/// point in p's cell or one of its 26 neighbours (within size, never farther than 2·√3·size).
class CellSet {
 public:
  CellSet(double size, std::size_t expected_cells) : inv_(static_cast<float>(1.0 / size)), index_(expected_cells) {}
  void insert(const Eigen::Vector3f& p) { index_.insert(detail::cell_key(detail::cell_of(p, inv_))); }
  [[nodiscard]] bool near(const Eigen::Vector3f& p) const {
    const Eigen::Vector3i c = detail::cell_of(p, inv_);
    for (int a = -1; a <= 1; ++a)
      for (int b = -1; b <= 1; ++b)
        for (int d = -1; d <= 1; ++d)
          if (index_.find(detail::cell_key(c + Eigen::Vector3i(a, b, d))) >= 0) return true;
    return false;
  }

 private:
  float inv_;
  detail::CellIndex index_;
};

}  // namespace

Result<Registration> refine(const PreparedCloud& templ, const Cloud& scene, const Transform& initial,
                            const FineSettings& settings) {
  const auto& T = templ.impl();
  if (T.fine.size() < 6 || scene.size() < 6)
    return Error{"vision.too_few_points", "fine registration needs at least 6 points (template " +
                                              std::to_string(T.fine.size()) + ", scene " + std::to_string(scene.size()) + ")"};
  const double voxel = T.settings.coarse_voxel;
  const double d_max = settings.max_distance > 0 ? settings.max_distance : 2.0 * voxel;
  // Not tighter than half a coarse voxel: with a tiny distance, correspondences that are
  // still off by the coarse error are dropped and dense sensor-fixed patterns (LiDAR rings)
  // pull the pose back towards identity.
  const double d_min = std::min(d_max, settings.min_distance > 0 ? settings.min_distance
                                                                  : std::max(3.0 * T.fine_spacing, 0.5 * voxel));
  int at_min = 0;
  const int threads = detail::thread_count(settings.threads);

  Transform T_template_scene = initial.inverse();
  double d = d_max;
  bool converged = false;
  int it = 0;
  using Mat6 = Eigen::Matrix<double, 6, 6>;
  using Vec6 = Eigen::Matrix<double, 6, 1>;
  std::vector<Mat6> Hs(static_cast<std::size_t>(threads), Mat6::Zero());
  std::vector<Vec6> gs(static_cast<std::size_t>(threads), Vec6::Zero());
  std::vector<std::size_t> ns(static_cast<std::size_t>(threads), 0);
  // Robust weights (Tukey) at the final distance: scale from the last iteration's residuals.
  std::vector<std::vector<float>> residuals(static_cast<std::size_t>(threads));
  double tukey = std::numeric_limits<double>::infinity();
  std::vector<std::uint8_t> outside;
  std::optional<CellSet> near_material;  // trim_neighbourhood_mm: the last iteration's trimmed points
  // heights_only_slope_deg: a template normal with a larger z than this is on such a face
  const float heights_only_nz = settings.heights_only_slope_deg > 0
                                    ? static_cast<float>(std::cos(deg_to_rad(settings.heights_only_slope_deg)))
                                    : 2.0f;
  if (settings.edge_aware) T.find_edges();
  // degenerate_ratio: steps about the template's centroid c, rotations scaled by its RMS
  // radius L (mm), so that rotation and translation eigenvalues compare
  const bool remap = settings.degenerate_ratio > 0;
  Eigen::Vector3f c = Eigen::Vector3f::Zero();
  double L = 1.0;
  if (remap) {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (const auto& p : T.fine.points) sum += p.cast<double>();
    c = (sum / static_cast<double>(T.fine.size())).cast<float>();
    double s2 = 0;
    for (const auto& p : T.fine.points) s2 += (p - c).squaredNorm();
    L = std::max(1e-6, std::sqrt(s2 / static_cast<double>(T.fine.size())));
  }
  std::vector<std::uint8_t> on_flat;  // flat_sample: scene point i matched a flat face
  const auto flat_sample = static_cast<std::size_t>(std::max(1, settings.flat_sample));
  for (; it < settings.max_iterations; ++it) {
    const Eigen::Matrix3f R = T_template_scene.rotation().cast<float>();
    const Eigen::Vector3f t = T_template_scene.translation().cast<float>();
    const auto d2max = static_cast<float>(d * d);
    // While the correspondence distance is still shrinking a subset of the scene is enough;
    // the final iterations use every point (full resolution).
    const std::size_t stride = d > d_min ? std::max<std::size_t>(1, scene.size() / settings.coarse_points) : 1;
    const bool use_grid = T.grid && d <= T.settings.nearest_grid_band;
    const bool robust = settings.robust && d <= d_min;
    const bool trim = settings.trim_outside_mm > 0 && d <= d_min;
    // trim_neighbourhood_mm: mark the points trimmed in this full-resolution iteration, leave
    // out their neighbourhood in the next one
    const bool mark = trim && settings.trim_neighbourhood_mm > 0 && stride == 1;
    const bool use_near = mark && near_material.has_value();
    if (mark) outside.assign(scene.size(), 0);
    // flat_sample: the first full-resolution iteration finds the points on flat faces, the
    // next ones use every flat_sample-th of them (with that weight) and every other point
    const bool thin_flat = settings.flat_sample > 1 && heights_only_nz <= 1.0f && stride == 1;
    const bool sample_flat = thin_flat && !on_flat.empty();
    if (thin_flat && on_flat.empty()) on_flat.assign(scene.size(), 0);
    detail::parallel_for(scene.size() / stride, threads, [&](std::size_t th, std::size_t b, std::size_t e) {
      Mat6 H = Mat6::Zero();
      Vec6 g = Vec6::Zero();
      std::size_t cnt = 0;
      auto& res = residuals[th];
      res.clear();
      for (std::size_t k = b; k < e; ++k) {
        const std::size_t i = k * stride;
        if (sample_flat && on_flat[i] != 0 && i % flat_sample != 0) continue;
        const Eigen::Vector3f q = R * scene.points[i] + t;
        auto [j, d2] = use_grid ? T.nearest_fine(q) : detail::nearest(*T.fine_tree, q);
        if (j < 0 || d2 > d2max) continue;
        // j becomes the point whose tangent plane measured r (the edge partner at an edge)
        double r = settings.edge_aware ? T.edge_residual(q, j)
                                       : T.fine.normals[static_cast<std::size_t>(j)].dot(q - T.fine.points[static_cast<std::size_t>(j)]);
        const Eigen::Vector3f& nj = T.fine.normals[static_cast<std::size_t>(j)];
        // heights_only_slope_deg: measured vertically, fixing only z, roll and pitch
        const bool flat = nj.z() > heights_only_nz;
        const Eigen::Vector3f nm = flat ? Eigen::Vector3f::UnitZ() : nj;
        if (flat) r /= static_cast<double>(nj.z());
        double w = 1.0;
        if (trim && r > settings.trim_outside_mm) {
          if (mark) outside[i] = 1;
          continue;
        }
        if (use_near && near_material->near(scene.points[i])) continue;
        if (thin_flat) {
          on_flat[i] = flat ? 1 : 0;
          if (flat && sample_flat) w = static_cast<double>(flat_sample);
        }
        if (robust) {
          res.push_back(static_cast<float>(std::abs(r)));
          if (std::abs(r) >= tukey) continue;
          const double u = r / tukey;
          w = (1.0 - u * u) * (1.0 - u * u);
        }
        Vec6 J;
        J.head<3>() = (q - c).cross(nm).cast<double>();
        J.tail<3>() = nm.cast<double>();
        H.noalias() += w * J * J.transpose();
        g.noalias() += (w * r) * J;
        ++cnt;
      }
      Hs[th] = H;
      gs[th] = g;
      ns[th] = cnt;
    });
    Mat6 H = Mat6::Zero();
    Vec6 g = Vec6::Zero();
    std::size_t cnt = 0;
    if (settings.occluding_edges != nullptr && stride == 1 && settings.edge_weight > 0) {
      // occluding_edges: each against the wall under the nearest template edge
      const double band = settings.trim_outside_mm > 0 ? settings.trim_outside_mm : d;
      // A wall: a normal within about 17 degrees of level. The template's samples at the edge
      // itself average the two faces' normals (0.5 mm voxels); against those the edges pulled
      // the boss 0.029 mm (median, 50 seeds) with 45 degrees, 0.027 mm with 17.
      const float steep = 0.3f;
      for (const auto& p : settings.occluding_edges->points) {
        const Eigen::Vector3f q = R * p + t;
        auto [j, d2] = use_grid ? T.nearest_fine(q) : detail::nearest(*T.fine_tree, q);
        if (j < 0 || d2 > d2max) continue;
        auto k = static_cast<std::size_t>(j);
        if (!T.edge_partner.empty() && T.edge_partner[k] >= 0) {
          const auto e = static_cast<std::size_t>(T.edge_partner[k]);
          if (std::abs(T.fine.normals[e].z()) < std::abs(T.fine.normals[k].z())) k = e;
        }
        const Eigen::Vector3f& nm = T.fine.normals[k];
        if (std::abs(nm.z()) > steep) continue;
        const double r = nm.dot(q - T.fine.points[k]);
        if (std::abs(r) > band) continue;
        Vec6 J;
        J.head<3>() = (q - c).cross(nm).cast<double>();
        J.tail<3>() = nm.cast<double>();
        H.noalias() += settings.edge_weight * J * J.transpose();
        g.noalias() += (settings.edge_weight * r) * J;
      }
    }
    for (std::size_t th = 0; th < Hs.size(); ++th) {
      H += Hs[th];
      g += gs[th];
      cnt += ns[th];
      Hs[th].setZero();
      gs[th].setZero();
      ns[th] = 0;
    }
    if (mark) {
      const auto n = static_cast<std::size_t>(std::count(outside.begin(), outside.end(), std::uint8_t{1}));
      near_material.reset();
      if (n > 0) {
        near_material.emplace(settings.trim_neighbourhood_mm, n);
        for (std::size_t i = 0; i < scene.size(); ++i)
          if (outside[i] != 0) near_material->insert(scene.points[i]);
      }
    }
    if (cnt < 6)
      return Error{"vision.too_few_points", "fine registration: only " + std::to_string(cnt) +
                                                " scene points near the template surface (is the part in the scan?)"};
    if (robust) {
      // Tukey's c = 4.685 sigma, sigma from the median absolute residual; never tighter than
      // a tenth of the final distance (noise-free data).
      std::vector<float> all;
      for (auto& v : residuals) all.insert(all.end(), v.begin(), v.end());
      if (!all.empty()) {
        std::nth_element(all.begin(), all.begin() + static_cast<std::ptrdiff_t>(all.size() / 2), all.end());
        tukey = std::max(0.1 * d_min, 4.685 * 1.4826 * static_cast<double>(all[all.size() / 2]));
      }
    }
    // A region that is mostly one flat face does not constrain sliding along it (nor turning
    // about its normal): H is near singular there and the plain solve returned steps of 1e12 mm.
    // With degenerate_ratio such directions get no step at all; without it, a small floor on
    // the diagonal (relative to the best-constrained rotation and translation) keeps them
    // near where the whole-part pose put them. No step may exceed the correspondence distance.
    Vec6 x;
    if (remap) {
      // degenerate_ratio: solve in the eigenbasis of the scaled normal matrix, no step along
      // directions below the ratio
      Vec6 scale;
      scale << 1.0 / L, 1.0 / L, 1.0 / L, 1.0, 1.0, 1.0;
      const Mat6 H_scaled = scale.asDiagonal() * H * scale.asDiagonal();
      const Eigen::SelfAdjointEigenSolver<Mat6> eig(H_scaled);
      const Vec6 lambda = eig.eigenvalues();
      const Vec6 gv = eig.eigenvectors().transpose() * (scale.asDiagonal() * g);
      Vec6 y = Vec6::Zero();
      for (int k = 0; k < 6; ++k)
        if (lambda(k) > settings.degenerate_ratio * lambda(5)) y(k) = -gv(k) / lambda(k);
      x = scale.asDiagonal() * (eig.eigenvectors() * y);
    } else {
      const double floor_r = 1e-4 * H.diagonal().head<3>().maxCoeff();
      const double floor_t = 1e-4 * H.diagonal().tail<3>().maxCoeff();
      for (int k = 0; k < 3; ++k) {
        H(k, k) += floor_r;
        H(k + 3, k + 3) += floor_t;
      }
      x = H.ldlt().solve(-g);
    }
    if (!x.allFinite()) break;
    if (const double tn = x.tail<3>().norm(); tn > d) x *= d / tn;
    Transform step = Transform::Identity();
    const double angle = x.head<3>().norm();
    if (angle > 0) step.linear() = Eigen::AngleAxisd(angle, x.head<3>() / angle).toRotationMatrix();
    // about c: p -> R (p - c) + c + t (c = 0 without degenerate_ratio)
    step.translation() = x.tail<3>() + c.cast<double>() - step.linear() * c.cast<double>();
    T_template_scene = step * T_template_scene;
    const bool small = x.tail<3>().norm() < settings.convergence_translation * voxel && angle < settings.convergence_rotation_rad;
    if (d <= d_min) ++at_min;
    // With robust weights, the first iteration at d_min only measures the residuals' scale.
    if ((small && d <= d_min && (!settings.robust || at_min >= 3)) || at_min >= 8) {
      converged = small;
      ++it;
      break;
    }
    if (small || it >= 3) d = std::max(d_min, d * 0.7);
  }
  // Fitness on at most ~20000 template points (a sample of large templates is as telling).
  Registration r = evaluate_strided(T.fine, scene, T_template_scene.inverse(),
                                    settings.fitness_distance > 0 ? settings.fitness_distance : d_min,
                                    T.fine.size() / 20000 + 1,
                                    Visibility{settings.viewpoint, settings.max_view_angle_deg, settings.covered_mm});
  r.iterations = it;
  r.converged = converged;
  return r;
}

Result<Registration> locate(const Cloud& templ, const Cloud& scene, const LocateSettings& settings) {
  if (templ.size() < 10)
    return Error{"vision.too_few_points", "the template has " + std::to_string(templ.size()) + " valid points (at least 10)"};
  if (scene.size() < 10)
    return Error{"vision.too_few_points", "the scene has " + std::to_string(scene.size()) + " valid points (at least 10)"};
  {
    // Any unit works, but both clouds must share it: a template far larger than the scene (or a
    // scene a thousand times larger) means millimetres against metres.
    const double te = bounds(templ).diagonal();
    const double se = bounds(scene).diagonal();
    if (te > 50.0 * se || se > 500.0 * te) {
      std::ostringstream m;
      m << "the template spans " << te << " units and the scene " << se
        << ": they look like different units (millimetres against metres?); convert one of them";
      return Error{"vision.units", m.str()};
    }
  }
  // Scale-free voxel: about `coarse_points` template points, never finer than the data.
  double voxel = voxel_for_count(templ, settings.coarse_points);
  PrepareSettings ps;
  {
    // Median nearest-neighbour spacing of the template, from a sample.
    const auto tree = detail::make_tree(templ.points);
    std::vector<float> d;
    pcl::Indices idx(2);
    std::vector<float> d2(2);
    const std::size_t step = std::max<std::size_t>(1, templ.size() / 1000);
    for (std::size_t i = 0; i < templ.size(); i += step) {
      pcl::PointXYZ q;
      q.getVector3fMap() = templ.points[i];
      if (tree->nearestKSearch(q, 2, idx, d2) == 2) d.push_back(std::sqrt(d2[1]));
    }
    std::sort(d.begin(), d.end());
    const double spacing = d.empty() ? 0.0 : d[d.size() / 2];
    voxel = std::max(voxel, 1.5 * spacing);
  }
  if (!(voxel > 0)) return Error{"vision.too_few_points", "the template has no extent (all points coincide)"};
  ps.coarse_voxel = voxel;
  ps.feature_radius = settings.feature_radius_voxels * voxel;
  // Uniform density for ICP: dense patches (LiDAR rings near the sensor, sensor-fixed
  // structure) would otherwise dominate the objective and pull towards identity.
  const double icp_voxel = voxel / 3.0;
  const auto t_prep = PreparedCloud::prepare(voxel_downsample(templ, icp_voxel), ps);
  FineSettings fine_settings = settings.fine;
  if (fine_settings.fitness_distance <= 0) fine_settings.fitness_distance = voxel;
  // The scene needs no fine normals: ICP uses the template's.
  const Cloud scene_u = voxel_downsample(scene, icp_voxel);
  Cloud scene_n = scene_u;
  estimate_normals(scene_n, 8);  // oriented towards the sensor (origin), as for a scan
  const auto s_prep = PreparedCloud::prepare(scene_n, ps);

  std::vector<Transform> candidates{Transform::Identity()};
  auto coarse = coarse_align(t_prep, s_prep, settings.coarse);
  if (coarse) candidates.insert(candidates.begin(), coarse->T_scene_template);

  std::optional<Registration> best;
  const Bounds tb = bounds(templ);
  for (const auto& c : candidates) {
    // Only scene points near the placed template take part in ICP.
    const Eigen::Vector3d margin = Eigen::Vector3d::Constant(3.0 * voxel);
    const Cloud near = crop_box(scene_u, c.inverse(), tb.min.cast<double>() - margin, tb.max.cast<double>() + margin);
    auto fine = refine(t_prep, near.size() >= 6 ? near : scene_u, c, fine_settings);
    if (!fine) continue;
    if (!best || fine->fitness > best->fitness) best = *fine;
  }
  if (!best) return coarse ? Error{"vision.no_match", "fine registration failed for every candidate pose", ErrorKind::wrong_part} : coarse.error();
  if (best->fitness < settings.min_fitness) {
    return Error{"vision.no_match", "the template was not found in the scene: best fitness " + std::to_string(best->fitness) +
                                        " is below " + std::to_string(settings.min_fitness) +
                                        " (is the object in the scan, and are both clouds in the same unit?)", ErrorKind::wrong_part};
  }
  return *best;
}

}  // namespace fettle::vision
