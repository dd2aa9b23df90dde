// PCL Moving Least Squares driver for benches/compare_cgal_pcl.sh.
//
//   pcl_mls IN.xyz OUT.xyz RADIUS_FACTOR [ORDER] [THREADS]
//
// Smooths with pcl::MovingLeastSquares<PointXYZ, PointXYZ>: polynomial order ORDER (default 2),
// search radius = RADIUS_FACTOR x the mean nearest-neighbour distance of the input cloud (measured
// here with PCL's k-d tree; the Gaussian weight parameter is radius^2, PCL's default for
// setSearchRadius), no upsampling, PCL's default projection (SIMPLE), THREADS OpenMP threads
// (default 2). PCL drops points with fewer than 3 neighbours in the radius; the point count is
// printed.
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>
#include <pcl/surface/mls.h>
#include <pcl/pcl_config.h>

#include <cmath>
#include <iostream>

#include "xyz_io.h"

int main(int argc, char** argv) {
  try {
    if (argc < 4) {
      std::cerr << "usage: pcl_mls IN OUT RADIUS_FACTOR [ORDER] [THREADS]\n";
      return 2;
    }
    const std::string in = argv[1], out = argv[2];
    const double factor = std::atof(argv[3]);
    const int order = argc > 4 ? std::atoi(argv[4]) : 2;
    const unsigned threads = argc > 5 ? static_cast<unsigned>(std::atoi(argv[5])) : 2u;
    std::cerr << "pcl_mls: PCL " << PCL_VERSION_PRETTY << "\n";

    auto t0 = std::chrono::steady_clock::now();
    const auto raw = read_xyz(in);
    pcl::PointCloud<pcl::PointXYZ>::Ptr cloud(new pcl::PointCloud<pcl::PointXYZ>);
    cloud->reserve(raw.size());
    for (const auto& p : raw)
      cloud->push_back(pcl::PointXYZ(static_cast<float>(p[0]), static_cast<float>(p[1]),
                                     static_cast<float>(p[2])));
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
    write_xyz(out, result.begin(), result.end(), [](const pcl::PointXYZ& p) {
      return std::array<double, 3>{p.x, p.y, p.z};
    });
    const double write_s = seconds_since(t2);
    std::printf(
        "{\"output\": \"%s\", \"wall_s\": %.6f, \"compute_s\": %.6f, \"points\": %zu, "
        "\"input_points\": %zu, \"spacing\": %.9g, \"radius\": %.9g}\n",
        out.c_str(), read_s + compute_s + write_s, compute_s, result.size(), cloud->size(),
        spacing, radius);
  } catch (const std::exception& e) {
    std::cerr << "pcl_mls: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
