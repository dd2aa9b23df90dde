// Minimal ASCII XYZ reader/writer shared by the comparison drivers (benches/compare_cgal_pcl.sh,
// benches/real_scans.sh). Reads the first three numbers of every line that starts with one (lines
// starting with anything else, such as qemd's "# x y z ..." header, are skipped; "NaN" is a
// number); writes "x y z" with the shortest digits that read back to the same doubles (exact for
// any input, also for LAS coordinates in the millions).
#pragma once
#include <array>
#include <charconv>
#include <chrono>
#include <cmath>
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
    char buf[3 * 32 + 4];
    char* c = buf;
    for (int i = 0; i < 3; ++i) {
      if (i) *c++ = ' ';
      if (std::isfinite(p[i])) {
        c = std::to_chars(c, buf + sizeof buf, p[i]).ptr;
      } else {
        const char* t = std::isnan(p[i]) ? "NaN" : (p[i] > 0 ? "inf" : "-inf");
        while (*t) *c++ = *t++;
      }
    }
    *c++ = '\n';
    std::fwrite(buf, 1, static_cast<std::size_t>(c - buf), f);
  }
  if (std::fclose(f) != 0) throw std::runtime_error("error writing " + path);
}

inline bool is_finite(const std::array<double, 3>& p) {
  return std::isfinite(p[0]) && std::isfinite(p[1]) && std::isfinite(p[2]);
}

inline double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
