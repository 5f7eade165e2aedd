// Gray-code structured light for camera-projector calibration (Moreno & Taubin 2012).
#include "fettle/vision/calibration/gray_code.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "fettle/core/error.hpp"

namespace fettle::vision::calibration {

namespace {

int bits_for(int n) {
  int b = 0;
  while ((1 << b) < n) ++b;
  return std::max(b, 1);
}

std::string two_digits(int b) {
  char buf[16];
  std::snprintf(buf, sizeof buf, "%02d", b);
  return buf;
}

GrayImage blank(const GrayCodeLayout& l, const std::string& name, std::uint8_t value) {
  GrayImage g;
  g.name = name;
  g.width_px = l.width_px;
  g.height_px = l.height_px;
  g.pixels.assign(static_cast<std::size_t>(l.width_px) * static_cast<std::size_t>(l.height_px), value);
  return g;
}

}  // namespace

GrayCodeLayout GrayCodeLayout::for_projector(int width_px, int height_px) {
  if (width_px < 2 || height_px < 2 || width_px > 16384 || height_px > 16384)
    throw UserError("projector size " + std::to_string(width_px) + "x" + std::to_string(height_px) +
                    " px: expected WIDTHxHEIGHT between 2 and 16384 px each, e.g. 1280x800");
  GrayCodeLayout l;
  l.width_px = width_px;
  l.height_px = height_px;
  l.column_bits = bits_for(width_px);
  l.row_bits = bits_for(height_px);
  return l;
}

std::vector<std::string> GrayCodeLayout::names() const {
  std::vector<std::string> n{"white", "black"};
  for (int b = 0; b < column_bits; ++b) {
    n.push_back("col_" + two_digits(b));
    n.push_back("col_" + two_digits(b) + "_inv");
  }
  for (int b = 0; b < row_bits; ++b) {
    n.push_back("row_" + two_digits(b));
    n.push_back("row_" + two_digits(b) + "_inv");
  }
  return n;
}

std::vector<GrayImage> gray_code_patterns(const GrayCodeLayout& l) {
  const auto names = l.names();
  std::vector<GrayImage> out;
  out.reserve(l.image_count());
  out.push_back(blank(l, names[0], 255));
  out.push_back(blank(l, names[1], 0));
  std::size_t k = 2;
  const auto add = [&](int bits, bool columns) {
    for (int b = 0; b < bits; ++b) {
      const int shift = bits - 1 - b;
      GrayImage p = blank(l, names[k++], 0), inv = blank(l, names[k++], 0);
      for (int v = 0; v < l.height_px; ++v)
        for (int u = 0; u < l.width_px; ++u) {
          const int c = columns ? u : v;
          const bool on = (((c ^ (c >> 1)) >> shift) & 1) != 0;
          const std::size_t i =
              static_cast<std::size_t>(v) * static_cast<std::size_t>(l.width_px) + static_cast<std::size_t>(u);
          p.pixels[i] = on ? 255 : 0;
          inv.pixels[i] = on ? 0 : 255;
        }
      out.push_back(std::move(p));
      out.push_back(std::move(inv));
    }
  };
  add(l.column_bits, true);
  add(l.row_bits, false);
  return out;
}

Result<ProjectorMap> decode_gray_code(const std::vector<GrayImage>& images, const GrayCodeLayout& l,
                                      const GrayDecodeOptions& o) {
  if (images.size() != l.image_count())
    return Error{"calibration.pattern_count",
                 "Gray-code decode for a " + std::to_string(l.width_px) + "x" + std::to_string(l.height_px) +
                     " px projector needs " + std::to_string(l.image_count()) + " images (white, black, " +
                     std::to_string(l.column_bits) + " column and " + std::to_string(l.row_bits) +
                     " row patterns each with its inverse), got " + std::to_string(images.size())};
  const int w = images[0].width_px, h = images[0].height_px;
  for (const auto& im : images)
    if (im.width_px != w || im.height_px != h ||
        im.pixels.size() != static_cast<std::size_t>(w) * static_cast<std::size_t>(h))
      return Error{"calibration.image_size", im.name + ": " + std::to_string(im.width_px) + "x" +
                                                 std::to_string(im.height_px) + " px, but " + images[0].name + " is " +
                                                 std::to_string(w) + "x" + std::to_string(h) +
                                                 " px; all pattern images of a pose must come from the same camera"};
  ProjectorMap m;
  m.width_px = w;
  m.height_px = h;
  const std::size_t n = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
  m.column.assign(n, -1);
  m.row.assign(n, -1);
  const auto& white = images[0].pixels;
  const auto& black = images[1].pixels;
  // Decodes `bits` pattern/inverse pairs starting at image `first`; -1 when a bit is undecidable.
  const auto decode = [&](std::size_t i, std::size_t first, int bits, double margin) {
    int gray_bit = 0, binary = 0;
    for (int b = 0; b < bits; ++b) {
      const int d = static_cast<int>(images[first + 2 * static_cast<std::size_t>(b)].pixels[i]) -
                    static_cast<int>(images[first + 2 * static_cast<std::size_t>(b) + 1].pixels[i]);
      if (std::abs(d) < margin) return -1;
      gray_bit = d > 0 ? 1 : 0;
      binary = (binary << 1) | ((binary & 1) ^ gray_bit);  // binary bit = previous binary bit xor gray bit
    }
    return binary;
  };
  const std::size_t first_row = 2 + 2 * static_cast<std::size_t>(l.column_bits);
  for (std::size_t i = 0; i < n; ++i) {
    const double contrast = static_cast<double>(white[i]) - static_cast<double>(black[i]);
    if (contrast < o.min_contrast_grey) {
      ++m.low_contrast_pixels;
      continue;
    }
    const double margin = std::max(o.min_bit_margin_grey, o.min_bit_margin_fraction * contrast);
    const int c = decode(i, 2, l.column_bits, margin);
    const int r = c < 0 ? -1 : decode(i, first_row, l.row_bits, margin);
    if (c < 0 || r < 0 || c >= l.width_px || r >= l.height_px) {
      ++m.undecided_pixels;
      continue;
    }
    m.column[i] = c;
    m.row[i] = r;
    ++m.valid_pixels;
  }
  return m;
}

std::size_t ProjectorCorners::found_count() const {
  return static_cast<std::size_t>(std::count(found.begin(), found.end(), true));
}

ProjectorCorners projector_corners(const ProjectorMap& m, const std::vector<Eigen::Vector2d>& corners,
                                   const ProjectorCornerOptions& o) {
  ProjectorCorners out;
  out.projector_px.assign(corners.size(), Eigen::Vector2d::Zero());
  out.found.assign(corners.size(), false);
  out.pixels_used.assign(corners.size(), 0);
  out.fit_rms_px.assign(corners.size(), 0.0);
  for (std::size_t k = 0; k < corners.size(); ++k) {
    const int cu = static_cast<int>(std::lround(corners[k].x())), cv_ = static_cast<int>(std::lround(corners[k].y()));
    std::vector<cv::Point2d> cam, proj;
    for (int v = std::max(0, cv_ - o.window_radius_px); v <= std::min(m.height_px - 1, cv_ + o.window_radius_px); ++v)
      for (int u = std::max(0, cu - o.window_radius_px); u <= std::min(m.width_px - 1, cu + o.window_radius_px); ++u) {
        const std::size_t i = m.index(u, v);
        if (m.column[i] < 0) continue;
        // Camera pixel (u, v) is centred at (u, v); it sees projector pixel (column, row),
        // which covers [column - 0.5, column + 0.5): unbiased.
        cam.emplace_back(u - corners[k].x(), v - corners[k].y());  // relative to the corner: better conditioned
        proj.emplace_back(m.column[i], m.row[i]);
      }
    if (cam.size() < std::max<std::size_t>(o.min_pixels, 8)) {
      out.pixels_used[k] = cam.size();
      continue;
    }
    cv::Mat H;
    for (int pass = 0; pass < 2; ++pass) {
      H = cv::findHomography(cam, proj, 0);
      if (H.empty()) break;
      std::vector<cv::Point2d> pred;
      cv::perspectiveTransform(cam, pred, H);
      std::vector<cv::Point2d> cam_kept, proj_kept;
      double sum2 = 0.0;
      for (std::size_t i = 0; i < cam.size(); ++i) {
        const double e = cv::norm(pred[i] - proj[i]);
        if (e > o.max_pixel_error_px) continue;
        cam_kept.push_back(cam[i]);
        proj_kept.push_back(proj[i]);
        sum2 += e * e;
      }
      const bool dropped = cam_kept.size() != cam.size();
      cam = std::move(cam_kept);
      proj = std::move(proj_kept);
      out.fit_rms_px[k] = cam.empty() ? 0.0 : std::sqrt(sum2 / static_cast<double>(cam.size()));
      if (!dropped || cam.size() < std::max<std::size_t>(o.min_pixels, 8)) break;
    }
    out.pixels_used[k] = cam.size();
    if (H.empty() || cam.size() < std::max<std::size_t>(o.min_pixels, 8)) continue;
    // The corner is at (0, 0) in the window's coordinates.
    const double wz = H.at<double>(2, 2);
    out.projector_px[k] = Eigen::Vector2d(H.at<double>(0, 2) / wz, H.at<double>(1, 2) / wz);
    out.found[k] = true;
  }
  return out;
}

Result<StructuredLightView> decode_stereo_view(const std::vector<GrayImage>& images, const BoardSpec& board,
                                               const GrayCodeLayout& layout, const StructuredLightOptions& o) {
  auto map = decode_gray_code(images, layout, o.decode);
  if (!map) return map.error();
  auto obs = detect_board(images[0], board, o.detect);
  if (!obs)
    return Error{obs.error().code,
                 images[0].name + " (the all-white pattern, where the board is looked for): " + obs.error().message};
  const auto pts = observed_points_mm(board, *obs);
  const auto pc = projector_corners(*map, obs->corners_px, o.corners);
  StructuredLightView out;
  out.corners_total = obs->corners_px.size();
  for (std::size_t k = 0; k < obs->corners_px.size(); ++k) {
    if (!pc.found[k]) continue;
    out.view.board_points_mm.push_back(pts[k]);
    out.view.camera_px.push_back(obs->corners_px[k]);
    out.view.projector_px.push_back(pc.projector_px[k]);
  }
  out.corners_decoded = out.view.camera_px.size();
  const auto need = static_cast<std::size_t>(std::ceil(o.min_corner_fraction * static_cast<double>(out.corners_total)));
  if (out.corners_decoded < std::max<std::size_t>(need, 6)) {
    std::size_t fewest = map->width_px * static_cast<std::size_t>(map->height_px);
    for (std::size_t k = 0; k < pc.found.size(); ++k)
      if (!pc.found[k]) fewest = std::min(fewest, pc.pixels_used[k]);
    return Error{"calibration.too_few_corners",
                 images[0].name + ": only " + std::to_string(out.corners_decoded) + " of " +
                     std::to_string(out.corners_total) + " board corners decoded in projector coordinates (need " +
                     std::to_string(std::max<std::size_t>(need, 6)) + "; a corner needs " +
                     std::to_string(o.corners.min_pixels) + " decoded pixels within " +
                     std::to_string(o.corners.window_radius_px) + " px, the undecoded ones had " +
                     std::to_string(fewest) + " or more). " + std::to_string(map->low_contrast_pixels) +
                     " pixels had too little contrast between the white and black patterns (shadow, board outside "
                     "the projected area, projector too dim) and " +
                     std::to_string(map->undecided_pixels) +
                     " had a stripe too close to call (defocus, camera noise): keep the whole board in the "
                     "projected area, in focus, and check the exposure"};
  }
  out.map = std::move(*map);
  return out;
}

}  // namespace fettle::vision::calibration
