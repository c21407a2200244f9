// The paper's workload frames for the OctoMap-side benchmark programs (octomap_bench.cpp,
// esdf_edt3d.cpp): a binary PCD file (float32 x y z, pose in VIEWPOINT tx ty tz qw qx qy
// qz) as an OctoMap point cloud in the world frame and its sensor origin.
#ifndef VOXMAP_BENCH_PCD_HPP
#define VOXMAP_BENCH_PCD_HPP

#include <octomap/octomap.h>

#include <fstream>
#include <sstream>
#include <string>
#include <vector>

struct Frame {
  octomap::Pointcloud cloud;
  octomap::point3d origin;
};

static bool read_pcd(const char* path, Frame& f) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  std::string line;
  size_t points = 0;
  double t[3] = {0, 0, 0}, q[4] = {1, 0, 0, 0};  // qw qx qy qz
  while (std::getline(in, line)) {
    std::istringstream s(line);
    std::string key;
    s >> key;
    if (key == "POINTS") s >> points;
    if (key == "VIEWPOINT") s >> t[0] >> t[1] >> t[2] >> q[0] >> q[1] >> q[2] >> q[3];
    if (key == "DATA") {
      std::string kind;
      s >> kind;
      if (kind != "binary") return false;
      break;
    }
  }
  std::vector<float> xyz(points * 3);
  in.read(reinterpret_cast<char*>(xyz.data()), std::streamsize(xyz.size() * sizeof(float)));
  if (!in) return false;
  octomath::Pose6D pose(octomath::Vector3(t[0], t[1], t[2]),
                        octomath::Quaternion(q[0], q[1], q[2], q[3]));
  for (size_t i = 0; i < points; ++i)
    f.cloud.push_back(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]);
  f.cloud.transform(pose);
  f.origin = octomap::point3d(t[0], t[1], t[2]);
  return true;
}

#endif
