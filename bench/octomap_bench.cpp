// OctoMap's own integration of the paper's workloads, for side-by-side figures with
// `voxmap bench` (bench/kernels_vs_octomap.sh builds and runs it). Each PCD frame (binary
// float32 x y z, pose in VIEWPOINT) is inserted into a fresh OcTree with OctoMap's
// defaults (the sensor model voxmap also uses) by insertPointCloud, at the given
// resolution and max range; prints the median and min of RUNS insertions in ms.
//
//   octomap_bench RESOLUTION MAX_RANGE RUNS FILE.pcd...
#include <octomap/octomap.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "pcd.hpp"

int main(int argc, char** argv) {
  if (argc < 5) {
    std::fprintf(stderr, "usage: %s RESOLUTION MAX_RANGE RUNS FILE.pcd...\n", argv[0]);
    return 2;
  }
  const double res = std::atof(argv[1]), range = std::atof(argv[2]);
  const int runs = std::atoi(argv[3]);
  for (int a = 4; a < argc; ++a) {
    Frame f;
    if (!read_pcd(argv[a], f)) {
      std::fprintf(stderr, "%s: not a binary x y z PCD\n", argv[a]);
      return 1;
    }
    std::vector<double> ms;
    for (int r = 0; r < runs; ++r) {
      octomap::OcTree tree(res);
      auto t0 = std::chrono::steady_clock::now();
      tree.insertPointCloud(f.cloud, f.origin, range);
      auto t1 = std::chrono::steady_clock::now();
      ms.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
    }
    std::sort(ms.begin(), ms.end());
    std::printf("%s octomap median %.1f min %.1f ms (%d runs)\n", argv[a], ms[ms.size() / 2],
                ms[0], runs);
  }
  return 0;
}
