// CGAL point-set smoothing driver for benches/compare_cgal_pcl.sh.
//
//   cgal_smooth jet       IN.xyz OUT.xyz    K
//   cgal_smooth bilateral IN.xyz OUT_PREFIX K SHARPNESS_DEG ITERATIONS NORMAL_K
//
// jet:       CGAL::jet_smooth_point_set (degree_fitting 2, degree_monge 2: CGAL's defaults) with K
//            neighbours, one pass.
// bilateral: normals by CGAL::pca_estimate_normals (NORMAL_K neighbours), oriented by
//            CGAL::mst_orient_normals (NORMAL_K neighbours), then ITERATIONS calls of
//            CGAL::bilateral_smooth_point_set (K neighbours, SHARPNESS_DEG), as in CGAL's
//            bilateral_smooth_point_set_example.cpp. Writes OUT_PREFIX.itN.xyz after every
//            iteration N, so one run gives the results of 1..ITERATIONS iterations.
//
// Both modes write the points in the input's order (mst_orient_normals reorders them; every
// point carries its input index, and the output is written back by that index), so output line i
// is input point i. Points with a non-finite coordinate are left out of the smoothing and written
// back unchanged (NaN stays NaN).
//
// Prints one JSON line per output file: the time a run stopping there would take (read + compute
// up to that output + one write), the compute time alone, the point count, and the number of
// non-finite input points passed through.
#include <CGAL/Simple_cartesian.h>
#include <CGAL/bilateral_smooth_point_set.h>
#include <CGAL/jet_smooth_point_set.h>
#include <CGAL/mst_orient_normals.h>
#include <CGAL/pca_estimate_normals.h>
#include <CGAL/property_map.h>
#include <CGAL/tags.h>

#include <iostream>
#include <tuple>
#include <utility>

#include "xyz_io.h"

typedef CGAL::Simple_cartesian<double> Kernel;
typedef Kernel::Point_3 Point;
typedef Kernel::Vector_3 Vector;
// Position, normal, index of the point in the input.
typedef std::tuple<Point, Vector, std::size_t> PointVectorIndex;

#ifdef CGAL_LINKED_WITH_TBB
typedef CGAL::Parallel_tag Concurrency_tag;
static const char* kConcurrency = "parallel (TBB)";
#else
typedef CGAL::Sequential_tag Concurrency_tag;
static const char* kConcurrency = "sequential";
#endif

static void report(const std::string& out, double read_s, double compute_s, double write_s,
                   std::size_t n, const std::string& extra = "") {
  std::printf("{\"output\": \"%s\", \"wall_s\": %.6f, \"compute_s\": %.6f, \"points\": %zu%s}\n",
              out.c_str(), read_s + compute_s + write_s, compute_s, n, extra.c_str());
  std::fflush(stdout);
}

int main(int argc, char** argv) {
  try {
    if (argc < 5) {
      std::cerr << "usage: cgal_smooth jet IN OUT K\n"
                   "       cgal_smooth bilateral IN OUT_PREFIX K SHARPNESS ITERS NORMAL_K\n";
      return 2;
    }
    const std::string mode = argv[1], in = argv[2], out = argv[3];
    const unsigned k = static_cast<unsigned>(std::atoi(argv[4]));
    std::cerr << "cgal_smooth: " << mode << ", CGAL " << CGAL_VERSION_STR << ", " << kConcurrency
              << "\n";
    auto t0 = std::chrono::steady_clock::now();
    const auto raw = read_xyz(in);
    const double read_s = seconds_since(t0);
    // The finite points go to CGAL; `out_pts` (the input, in order) receives the results.
    std::vector<std::array<double, 3>> out_pts = raw;
    std::vector<std::size_t> finite_idx;
    finite_idx.reserve(raw.size());
    for (std::size_t i = 0; i < raw.size(); ++i)
      if (is_finite(raw[i])) finite_idx.push_back(i);
    const std::size_t skipped = raw.size() - finite_idx.size();
    const std::string skipped_json = ", \"nonfinite_passed\": " + std::to_string(skipped);
    const auto get = [](const std::array<double, 3>& p) { return p; };
    if (mode == "jet") {
      std::vector<Point> pts;
      pts.reserve(finite_idx.size());
      for (std::size_t i : finite_idx) pts.emplace_back(raw[i][0], raw[i][1], raw[i][2]);
      auto t1 = std::chrono::steady_clock::now();
      // jet_smooth_point_set moves the points in place and keeps their order.
      CGAL::jet_smooth_point_set<Concurrency_tag>(pts, k);
      const double compute_s = seconds_since(t1);
      auto t2 = std::chrono::steady_clock::now();
      for (std::size_t j = 0; j < pts.size(); ++j)
        out_pts[finite_idx[j]] = {pts[j].x(), pts[j].y(), pts[j].z()};
      write_xyz(out, out_pts.begin(), out_pts.end(), get);
      report(out, read_s, compute_s, seconds_since(t2), out_pts.size(), skipped_json);
    } else if (mode == "bilateral") {
      if (argc < 8) {
        std::cerr << "bilateral needs K SHARPNESS ITERS NORMAL_K\n";
        return 2;
      }
      const double sharpness = std::atof(argv[5]);
      const int iterations = std::atoi(argv[6]);
      const unsigned normal_k = static_cast<unsigned>(std::atoi(argv[7]));
      std::vector<PointVectorIndex> pts;
      pts.reserve(finite_idx.size());
      for (std::size_t i : finite_idx)
        pts.emplace_back(Point(raw[i][0], raw[i][1], raw[i][2]), Vector(0, 0, 0), i);
      const auto point_map = CGAL::Nth_of_tuple_property_map<0, PointVectorIndex>();
      const auto normal_map = CGAL::Nth_of_tuple_property_map<1, PointVectorIndex>();
      auto t1 = std::chrono::steady_clock::now();
      CGAL::pca_estimate_normals<Concurrency_tag>(
          pts, normal_k, CGAL::parameters::point_map(point_map).normal_map(normal_map));
      // mst_orient_normals reorders the range and moves the points it could not orient to the
      // end; they are kept (with their unoriented PCA normals), so every input point is in the
      // output, and the carried index puts it back in its place.
      auto unoriented_begin = CGAL::mst_orient_normals(
          pts, normal_k, CGAL::parameters::point_map(point_map).normal_map(normal_map));
      const std::size_t unoriented = static_cast<std::size_t>(pts.end() - unoriented_begin);
      double compute_s = seconds_since(t1);
      for (int it = 1; it <= iterations; ++it) {
        auto t2 = std::chrono::steady_clock::now();
        CGAL::bilateral_smooth_point_set<Concurrency_tag>(
            pts, k,
            CGAL::parameters::point_map(point_map).normal_map(normal_map).sharpness_angle(
                sharpness));
        compute_s += seconds_since(t2);
        const std::string path = out + ".it" + std::to_string(it) + ".xyz";
        auto t3 = std::chrono::steady_clock::now();
        for (const auto& p : pts) {
          const Point& q = std::get<0>(p);
          out_pts[std::get<2>(p)] = {q.x(), q.y(), q.z()};
        }
        write_xyz(path, out_pts.begin(), out_pts.end(), get);
        report(path, read_s, compute_s, seconds_since(t3), out_pts.size(),
               ", \"unoriented\": " + std::to_string(unoriented) + skipped_json);
      }
    } else {
      std::cerr << "unknown mode " << mode << "\n";
      return 2;
    }
  } catch (const std::exception& e) {
    std::cerr << "cgal_smooth: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
