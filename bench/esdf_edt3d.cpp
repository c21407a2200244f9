// OctoMap's dynamicEDT3D (DynamicEDTOctomap) as an independent reference for voxmap's
// Euclidean distance field, for tests and benchmarks. Two modes:
//
// query: loads an OcTree (.bt), builds a DynamicEDTOctomap over the tree's metric bounding
//   box (the voxels from the first to the last known leaf, inclusive) with maxdist MAX_DIST
//   and update()s it; prints `bulk_ms <ms>` (construction + update) to stderr. For each
//   `x y z` line of QUERIES.txt prints `x y z d ox oy oz`: d from getDistance, the closest
//   obstacle (a voxel centre) from getDistanceAndClosestObstacle, or `nan nan nan` when it
//   gives none. dynamicEDT3D's values are printed raw: -1 outside its box, 0 in obstacle
//   cells, and its clamp (int(MAX_DIST/res)+1)*res where no obstacle is within reach.
//
// frames: incremental timing. One OcTree at RESOLUTION with OctoMap's defaults and a
//   DynamicEDTOctomap attached to it (its constructor turns on the tree's change
//   detection) over a fixed box covering all frames: every point clipped to MAX_RANGE
//   around its frame's origin, and the origins, padded by MAX_DIST. Per frame (binary PCD,
//   float32 x y z, pose in VIEWPOINT tx ty tz qw qx qy qz): insertPointCloud(cloud,
//   origin, MAX_RANGE), then edt.update(); prints
//   `frame <i> points <n> insert_ms <t> edt_ms <t>`, and at the end the median edt_ms of
//   frames 2..N and the first edt_ms. A sanity check of the update (outside the timed
//   region) goes to stderr: sampled endpoints of the frame that the tree holds occupied
//   must read 0, and the voxel next to each must read at most one voxel.
//
// UNKNOWN is `free` or `occupied` (dynamicEDT3D's treatUnknownAsOccupied).
//
//   esdf_edt3d query MAP.bt MAX_DIST UNKNOWN QUERIES.txt
//   esdf_edt3d frames RESOLUTION MAX_RANGE MAX_DIST UNKNOWN FILE.pcd...
//
// Build: g++ -O2 -o esdf_edt3d bench/esdf_edt3d.cpp -ldynamicedt3d -loctomap -loctomath
// (Debian: liboctomap-dev libdynamicedt3d-dev).
#include <dynamicEDT3D/dynamicEDTOctomap.h>
#include <octomap/octomap.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include "pcd.hpp"

static double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0)
      .count();
}

static bool parse_unknown(const char* s, bool& occupied) {
  if (!std::strcmp(s, "free")) occupied = false;
  else if (!std::strcmp(s, "occupied")) occupied = true;
  else return false;
  return true;
}

static int usage(const char* argv0) {
  std::fprintf(stderr,
               "usage: %s query MAP.bt MAX_DIST free|occupied QUERIES.txt\n"
               "       %s frames RESOLUTION MAX_RANGE MAX_DIST free|occupied FILE.pcd...\n",
               argv0, argv0);
  return 2;
}

static int run_query(int argc, char** argv) {
  if (argc != 6) return usage(argv[0]);
  const float max_dist = std::atof(argv[3]);
  bool unknown_occupied;
  if (!parse_unknown(argv[4], unknown_occupied)) return usage(argv[0]);

  octomap::OcTree tree(0.1);  // readBinary takes the resolution from the file
  if (!tree.readBinary(argv[2])) {
    std::fprintf(stderr, "%s: cannot read an OcTree\n", argv[2]);
    return 1;
  }
  if (tree.getNumLeafNodes() == 0) {
    std::fprintf(stderr, "%s: empty tree\n", argv[2]);
    return 1;
  }
  // The metric box runs from the lower face of the first leaf to the upper face of the
  // last; pass the centres of the first and last finest voxels so that rounding on the
  // faces can neither drop a boundary voxel nor add one beyond it.
  double x0, y0, z0, x1, y1, z1;
  tree.getMetricMin(x0, y0, z0);
  tree.getMetricMax(x1, y1, z1);
  const double h = tree.getResolution() / 2;
  const octomap::point3d bmin(x0 + h, y0 + h, z0 + h), bmax(x1 - h, y1 - h, z1 - h);

  auto t0 = std::chrono::steady_clock::now();
  DynamicEDTOctomap edt(max_dist, &tree, bmin, bmax, unknown_occupied);
  edt.update();
  std::fprintf(stderr, "bulk_ms %.3f\n", ms_since(t0));

  std::ifstream in(argv[5]);
  if (!in) {
    std::fprintf(stderr, "%s: cannot open\n", argv[5]);
    return 1;
  }
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream s(line);
    double x, y, z;
    if (!(s >> x >> y >> z)) continue;  // blank or comment line
    const octomap::point3d p(x, y, z);
    const float d = edt.getDistance(p);
    float d2 = 0;
    octomap::point3d o(nan, nan, nan);  // left untouched when there is no obstacle
    edt.getDistanceAndClosestObstacle(p, d2, o);
    if (std::isnan(o.x()))
      std::printf("%.6f %.6f %.6f %.6f nan nan nan\n", x, y, z, d);
    else
      std::printf("%.6f %.6f %.6f %.6f %.6f %.6f %.6f\n", x, y, z, d, o.x(), o.y(), o.z());
  }
  return 0;
}

static int run_frames(int argc, char** argv) {
  if (argc < 7) return usage(argv[0]);
  const double res = std::atof(argv[2]), range = std::atof(argv[3]);
  const float max_dist = std::atof(argv[4]);
  bool unknown_occupied;
  if (!parse_unknown(argv[5], unknown_occupied)) return usage(argv[0]);

  std::vector<Frame> frames(argc - 6);
  for (int a = 6; a < argc; ++a)
    if (!read_pcd(argv[a], frames[a - 6])) {
      std::fprintf(stderr, "%s: not a binary x y z PCD\n", argv[a]);
      return 1;
    }

  // Box: every ray end (clipped to the max range, as insertPointCloud casts it) and every
  // origin, padded by MAX_DIST.
  const double inf = std::numeric_limits<double>::infinity();
  double lo[3] = {inf, inf, inf}, hi[3] = {-inf, -inf, -inf};
  auto grow = [&](const octomap::point3d& p) {
    for (int k = 0; k < 3; ++k) {
      lo[k] = std::min(lo[k], double(p(k)));
      hi[k] = std::max(hi[k], double(p(k)));
    }
  };
  for (const Frame& f : frames) {
    grow(f.origin);
    for (size_t i = 0; i < f.cloud.size(); ++i) {
      octomap::point3d p = f.cloud[i];
      const octomap::point3d d = p - f.origin;
      const double len = d.norm();
      if (range > 0 && len > range) p = f.origin + d * float(range / len);
      grow(p);
    }
  }
  const octomap::point3d bmin(lo[0] - max_dist, lo[1] - max_dist, lo[2] - max_dist);
  const octomap::point3d bmax(hi[0] + max_dist, hi[1] + max_dist, hi[2] + max_dist);

  octomap::OcTree tree(res);
  auto t0 = std::chrono::steady_clock::now();
  // Its constructor calls tree.enableChangeDetection(true); update() then reads and
  // resets the tree's changed keys.
  DynamicEDTOctomap edt(max_dist, &tree, bmin, bmax, unknown_occupied);
  std::fprintf(stderr, "box %.3f %.3f %.3f .. %.3f %.3f %.3f init_ms %.3f\n", bmin.x(),
               bmin.y(), bmin.z(), bmax.x(), bmax.y(), bmax.z(), ms_since(t0));

  std::vector<double> edt_ms;
  for (size_t i = 0; i < frames.size(); ++i) {
    const Frame& f = frames[i];
    t0 = std::chrono::steady_clock::now();
    tree.insertPointCloud(f.cloud, f.origin, range);
    const double ins = ms_since(t0);
    t0 = std::chrono::steady_clock::now();
    edt.update();
    edt_ms.push_back(ms_since(t0));
    std::printf("frame %zu points %zu insert_ms %.3f edt_ms %.3f\n", i + 1, f.cloud.size(),
                ins, edt_ms.back());
    std::fflush(stdout);

    // Check (untimed): endpoints of this frame that are occupied in the tree read 0, and
    // the voxel one step along +x reads at most one voxel.
    size_t occ = 0, zero = 0, near = 0;
    const size_t stride = std::max<size_t>(1, f.cloud.size() / 200);
    for (size_t j = 0; j < f.cloud.size(); j += stride) {
      const octomap::point3d p = f.cloud[j];
      if (range > 0 && (p - f.origin).norm() > range) continue;
      const octomap::OcTreeNode* n = tree.search(p);
      if (!n || !tree.isNodeOccupied(n)) continue;
      ++occ;
      if (edt.getDistance(p) == 0) ++zero;
      const float dn = edt.getDistance(p + octomap::point3d(float(res), 0, 0));
      if (dn >= 0 && dn <= res * 1.0001) ++near;
    }
    std::fprintf(stderr, "check frame %zu occupied_endpoints %zu dist0 %zu next_le_res %zu\n",
                 i + 1, occ, zero, near);
  }

  std::vector<double> rest(edt_ms.begin() + 1, edt_ms.end());
  std::sort(rest.begin(), rest.end());
  if (rest.empty())
    std::printf("median_edt_ms nan (frames 2..%zu)\n", edt_ms.size());
  else
    std::printf("median_edt_ms %.3f (frames 2..%zu)\n", rest[rest.size() / 2], edt_ms.size());
  std::printf("first_edt_ms %.3f\n", edt_ms[0]);
  return 0;
}

int main(int argc, char** argv) {
  if (argc >= 2 && !std::strcmp(argv[1], "query")) return run_query(argc, argv);
  if (argc >= 2 && !std::strcmp(argv[1], "frames")) return run_frames(argc, argv);
  return usage(argv[0]);
}
