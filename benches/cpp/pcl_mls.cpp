// PCL Moving Least Squares driver for benches/compare_cgal_pcl.sh and benches/real_scans.sh.
//
//   pcl_mls IN.xyz OUT.xyz RADIUS_FACTOR [ORDER] [THREADS] [--ordered]
//
// Smooths with pcl::MovingLeastSquares<PointXYZ, PointXYZ>: polynomial order ORDER (default 2),
// search radius = RADIUS_FACTOR x the mean nearest-neighbour distance of the input cloud (measured
// here with PCL's k-d tree; the Gaussian weight parameter is radius^2, PCL's default for
// setSearchRadius), no upsampling, PCL's default projection (SIMPLE), THREADS OpenMP threads
// (default 2). PCL drops points with fewer than 3 neighbours in the radius, and with several
// threads it returns the points grouped by thread, not in the input's order.
//
// PCL works in float32: the cloud is moved to its centroid (computed in double) before the
// conversion and moved back after, so that coordinates in the millions (LAS, UTM) keep their
// precision. Points with a non-finite coordinate are never given to PCL.
//
// Without --ordered, OUT holds PCL's output as it comes (the dropped points are missing, the
// order is PCL's). With --ordered, OUT holds every input point in the input's order: each output
// point goes back to its input point through getCorrespondingIndices(), and an input point PCL
// produced nothing for (dropped, or non-finite in the input) is written at its input position;
// "missing" counts the finite ones, "nonfinite_passed" the non-finite ones.
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>
#include <pcl/surface/mls.h>
#include <pcl/pcl_config.h>

#include <cmath>
#include <cstring>
#include <iostream>

#include "xyz_io.h"

int main(int argc, char** argv) {
  try {
    std::vector<std::string> args;
    bool ordered = false;
    for (int i = 1; i < argc; ++i) {
      if (std::strcmp(argv[i], "--ordered") == 0) ordered = true;
      else args.emplace_back(argv[i]);
    }
    if (args.size() < 3) {
      std::cerr << "usage: pcl_mls IN OUT RADIUS_FACTOR [ORDER] [THREADS] [--ordered]\n";
      return 2;
    }
    const std::string in = args[0], out = args[1];
    const double factor = std::atof(args[2].c_str());
    const int order = args.size() > 3 ? std::atoi(args[3].c_str()) : 2;
    const unsigned threads = args.size() > 4 ? static_cast<unsigned>(std::atoi(args[4].c_str())) : 2u;
    std::cerr << "pcl_mls: PCL " << PCL_VERSION_PRETTY << "\n";

    auto t0 = std::chrono::steady_clock::now();
    const auto raw = read_xyz(in);
    std::vector<std::size_t> finite_idx;
    finite_idx.reserve(raw.size());
    double centre[3] = {0.0, 0.0, 0.0};
    for (std::size_t i = 0; i < raw.size(); ++i) {
      if (!is_finite(raw[i])) continue;
      finite_idx.push_back(i);
      for (int c = 0; c < 3; ++c) centre[c] += raw[i][c];
    }
    if (finite_idx.empty()) throw std::runtime_error("no finite point in " + in);
    for (int c = 0; c < 3; ++c) centre[c] /= static_cast<double>(finite_idx.size());
    pcl::PointCloud<pcl::PointXYZ>::Ptr cloud(new pcl::PointCloud<pcl::PointXYZ>);
    cloud->reserve(finite_idx.size());
    for (std::size_t i : finite_idx)
      cloud->push_back(pcl::PointXYZ(static_cast<float>(raw[i][0] - centre[0]),
                                     static_cast<float>(raw[i][1] - centre[1]),
                                     static_cast<float>(raw[i][2] - centre[2])));
    const double read_s = seconds_since(t0);

    auto t1 = std::chrono::steady_clock::now();
    pcl::search::KdTree<pcl::PointXYZ>::Ptr tree(new pcl::search::KdTree<pcl::PointXYZ>);
    tree->setInputCloud(cloud);
    // Mean distance to the nearest other point (k = 2: the point itself comes first).
    double spacing_sum = 0.0;
    pcl::Indices idx(2);
    std::vector<float> d2(2);
    for (std::size_t i = 0; i < cloud->size(); ++i) {
      tree->nearestKSearch((*cloud)[i], 2, idx, d2);
      spacing_sum += std::sqrt(static_cast<double>(d2[1]));
    }
    const double spacing = spacing_sum / static_cast<double>(cloud->size());
    const double radius = factor * spacing;

    pcl::MovingLeastSquares<pcl::PointXYZ, pcl::PointXYZ> mls;
    mls.setInputCloud(cloud);
    mls.setSearchMethod(tree);
    mls.setComputeNormals(false);
    mls.setPolynomialOrder(order);
    mls.setSearchRadius(radius);
    mls.setNumberOfThreads(threads);
    pcl::PointCloud<pcl::PointXYZ> result;
    mls.process(result);
    const double compute_s = seconds_since(t1);

    auto t2 = std::chrono::steady_clock::now();
    const auto back = [&](const pcl::PointXYZ& p) {
      return std::array<double, 3>{p.x + centre[0], p.y + centre[1], p.z + centre[2]};
    };
    std::string extra;
    std::size_t written = result.size();
    if (ordered) {
      const auto corr = mls.getCorrespondingIndices();
      if (!corr || corr->indices.size() != result.size())
        throw std::runtime_error("PCL gave no corresponding index for every output point");
      std::vector<std::array<double, 3>> out_pts = raw;
      std::vector<char> done(raw.size(), 0);
      std::size_t repeated = 0, nonfinite_out = 0;
      for (std::size_t j = 0; j < result.size(); ++j) {
        const std::size_t i = finite_idx.at(static_cast<std::size_t>(corr->indices[j]));
        if (done[i]) {
          ++repeated;  // more than one output for an input point: the first is kept
          continue;
        }
        done[i] = 1;
        out_pts[i] = back(result[j]);
        if (!is_finite(out_pts[i])) ++nonfinite_out;
      }
      std::size_t missing = 0;
      for (std::size_t i : finite_idx) missing += done[i] ? 0 : 1;
      write_xyz(out, out_pts.begin(), out_pts.end(), [](const std::array<double, 3>& p) {
        return p;
      });
      written = out_pts.size();
      extra = ", \"ordered\": true, \"missing\": " + std::to_string(missing) +
              ", \"repeated\": " + std::to_string(repeated) +
              ", \"nonfinite_out\": " + std::to_string(nonfinite_out) +
              ", \"nonfinite_passed\": " + std::to_string(raw.size() - finite_idx.size()) +
              ", \"mls_points\": " + std::to_string(result.size());
    } else {
      write_xyz(out, result.begin(), result.end(), back);
    }
    const double write_s = seconds_since(t2);
    std::printf(
        "{\"output\": \"%s\", \"wall_s\": %.6f, \"compute_s\": %.6f, \"points\": %zu, "
        "\"input_points\": %zu, \"spacing\": %.9g, \"radius\": %.9g%s}\n",
        out.c_str(), read_s + compute_s + write_s, compute_s, written, cloud->size(),
        spacing, radius, extra.c_str());
  } catch (const std::exception& e) {
    std::cerr << "pcl_mls: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
