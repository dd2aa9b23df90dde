// Minimal ASCII XYZ reader/writer shared by the comparison drivers (benches/compare_cgal_pcl.sh).
// Reads the first three numbers of every non-empty line; writes "x y z" with 9 significant digits
// (exact for the float32 inputs qemd writes).
#pragma once
#include <array>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

inline std::vector<std::array<double, 3>> read_xyz(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path);
  std::vector<std::array<double, 3>> pts;
  std::string line;
  while (std::getline(in, line)) {
    const char* s = line.c_str();
    char* end = nullptr;
    std::array<double, 3> p{};
    int n = 0;
    for (; n < 3; ++n) {
      p[n] = std::strtod(s, &end);
      if (end == s) break;
      s = end;
    }
    if (n == 3) pts.push_back(p);
    else if (n != 0) throw std::runtime_error("bad line in " + path + ": " + line);
  }
  return pts;
}

template <class It, class Get>
void write_xyz(const std::string& path, It begin, It end, Get get) {
  FILE* f = std::fopen(path.c_str(), "w");
  if (!f) throw std::runtime_error("cannot write " + path);
  for (It it = begin; it != end; ++it) {
    const std::array<double, 3> p = get(*it);
    std::fprintf(f, "%.9g %.9g %.9g\n", p[0], p[1], p[2]);
  }
  if (std::fclose(f) != 0) throw std::runtime_error("error writing " + path);
}

inline double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
