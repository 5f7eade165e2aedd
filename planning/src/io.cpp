// The planner's output files: trajectory.json and .csv (core's format) and preview.png.
#include "fettle/planning/io.hpp"

#include <cmath>
#include <fstream>
#include <iomanip>
#include <limits>
#include <sstream>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "fettle/core/atomic_file.hpp"
#include "fettle/core/error.hpp"

namespace fettle::planning {

Status write_preview_png(const std::filesystem::path& path, const std::vector<PreviewPoint>& cloud,
                         const Trajectory& trajectory) {
  // extent of everything drawn (base frame)
  Vec3 lo = Vec3::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
  for (const auto& p : cloud) lo = lo.cwiseMin(p.position_base_mm), hi = hi.cwiseMax(p.position_base_mm);
  for (const auto& p : trajectory.points)
    lo = lo.cwiseMin(p.T_base_tool.position_mm), hi = hi.cwiseMax(p.T_base_tool.position_mm);
  if (!lo.allFinite()) return Error{"planning.preview", path.string() + ": nothing to draw (no points, no trajectory)"};
  lo -= Vec3::Constant(5.0), hi += Vec3::Constant(5.0);
  const int panel = 600, margin = 20;
  const double scale = panel / std::max({hi.x() - lo.x(), hi.y() - lo.y(), hi.z() - lo.z(), 1.0});
  cv::Mat img(panel + 2 * margin + 20, 2 * panel + 3 * margin, CV_8UC3, cv::Scalar(30, 30, 30));
  double max_excess = 0.5;
  for (const auto& p : cloud) max_excess = std::max(max_excess, p.excess_mm);
  cv::Mat lut(1, 256, CV_8UC1);
  for (int i = 0; i < 256; ++i) lut.at<unsigned char>(0, i) = static_cast<unsigned char>(i);
  cv::Mat colors;
  cv::applyColorMap(lut, colors, cv::COLORMAP_TURBO);
  // view 0: top (x right, y up); view 1: side (x right, z up)
  auto to_px = [&](const Vec3& p, int view) {
    const double u = (p.x() - lo.x()) * scale;
    const double v = view == 0 ? (p.y() - lo.y()) * scale : (p.z() - lo.z()) * scale;
    return cv::Point(margin + view * (panel + margin) + static_cast<int>(u), margin + 20 + panel - static_cast<int>(v));
  };
  for (int view = 0; view < 2; ++view) {
    for (const auto& p : cloud) {
      const int c = static_cast<int>(std::clamp(p.excess_mm / max_excess, 0.0, 1.0) * 255.0);
      const auto col = p.excess_mm > 0 ? colors.at<cv::Vec3b>(0, c) : cv::Vec3b(110, 110, 110);
      const cv::Point px = to_px(p.position_base_mm, view);
      if (px.x >= 0 && px.y >= 0 && px.x < img.cols && px.y < img.rows) img.at<cv::Vec3b>(px) = col;
    }
    for (std::size_t i = 1; i < trajectory.points.size(); ++i) {
      const auto& a = trajectory.points[i - 1];
      const auto& b = trajectory.points[i];
      const bool grind = a.kind == MoveKind::grind && b.kind == MoveKind::grind;
      cv::line(img, to_px(a.T_base_tool.position_mm, view), to_px(b.T_base_tool.position_mm, view),
               grind ? cv::Scalar(255, 255, 255) : cv::Scalar(0, 200, 255), 1, cv::LINE_AA);
    }
    cv::putText(img, view == 0 ? "top (x-y), base frame" : "side (x-z), base frame",
                cv::Point(margin + view * (panel + margin), margin + 8), cv::FONT_HERSHEY_SIMPLEX, 0.5,
                cv::Scalar(230, 230, 230), 1, cv::LINE_AA);
  }
  std::vector<unsigned char> buf;
  if (!cv::imencode(".png", img, buf)) return Error{"planning.preview", path.string() + ": PNG encoding failed"};
  return write_file_atomic(path, std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
}

Status write_outputs(const std::filesystem::path& dir, const Trajectory& trajectory,
                     const std::vector<PreviewPoint>& cloud) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return Error{"planning.output", dir.string() + ": cannot create the output directory: " + ec.message()};
  if (Status s = write_trajectory_json(dir / "trajectory.json", trajectory); !s) return s;
  if (Status s = write_trajectory_csv(dir / "trajectory.csv", trajectory); !s) return s;
  return write_preview_png(dir / "preview.png", cloud, trajectory);
}

}  // namespace fettle::planning
