// A planner that checks a path against the live map: line of sight along each segment and
// a robot-sized box at each waypoint, plus a batched check of samples along the path.
//
//   planner PREFIX MAP x,y,z x,y,z ...   (beside `voxmap serve`; defaults: voxmap default)
#include <voxmap.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>

int main(int argc, char** argv) {
  if (argc < 5) {
    std::cerr << "usage: planner PREFIX MAP x,y,z x,y,z [...]\n";
    return 2;
  }
  std::vector<voxmap::Vec3> path;
  for (int i = 3; i < argc; ++i) {
    voxmap::Vec3 p{};
    if (std::sscanf(argv[i], "%lf,%lf,%lf", &p[0], &p[1], &p[2]) != 3) {
      std::cerr << "bad waypoint " << argv[i] << "\n";
      return 2;
    }
    path.push_back(p);
  }
  try {
    voxmap::Subscriber sub(argv[1], argv[2]);
    sub.wait(std::chrono::seconds(5));
    auto view = sub.latest();
    if (!view) {
      std::cerr << "no snapshot (is voxmap serve running?)\n";
      return 1;
    }
    auto [known, occupied] = view->counts();
    std::printf("snapshot %llu: %llu known, %llu occupied voxels\n",
                static_cast<unsigned long long>(view->sequence()),
                static_cast<unsigned long long>(known), static_cast<unsigned long long>(occupied));
    const double half = 0.2;  // the robot: a 0.4 m cube around each waypoint
    for (std::size_t i = 0; i + 1 < path.size(); ++i) {
      if (auto hit = view->first_hit(path[i], path[i + 1])) {
        std::printf("segment %zu: blocked at %.3f,%.3f,%.3f\n", i, (*hit)[0], (*hit)[1], (*hit)[2]);
      } else {
        std::printf("segment %zu: clear\n", i);
      }
    }
    for (std::size_t i = 0; i < path.size(); ++i) {
      const auto& p = path[i];
      bool free = view->is_box_free({p[0] - half, p[1] - half, p[2] - half},
                                    {p[0] + half, p[1] + half, p[2] + half}, /*unknown_is_free=*/true);
      std::printf("waypoint %zu: box %s\n", i, free ? "free" : "occupied");
    }
    // Samples every 5 cm along the path, checked in one call.
    std::vector<voxmap::Vec3> samples;
    for (std::size_t i = 0; i + 1 < path.size(); ++i)
      for (double t = 0; t < 1; t += 0.05 / std::max(1e-9, std::hypot(path[i + 1][0] - path[i][0],
                                                                          path[i + 1][1] - path[i][1],
                                                                          path[i + 1][2] - path[i][2])))
        samples.push_back({path[i][0] + t * (path[i + 1][0] - path[i][0]),
                           path[i][1] + t * (path[i + 1][1] - path[i][1]),
                           path[i][2] + t * (path[i + 1][2] - path[i][2])});
    std::size_t hits = 0;
    for (auto s : view->states_at(samples)) hits += s == voxmap::State::Occupied;
    std::printf("samples: %zu of %zu occupied\n", hits, samples.size());
  } catch (const voxmap::Error& e) {
    std::cerr << "voxmap: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
