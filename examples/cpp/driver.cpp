// A sensor driver that publishes a scan: a 64 x 48 depth image of a flat wall DISTANCE
// metres ahead (+x), written straight into shared memory and sent with its pose.
//
//   driver PREFIX MAP DISTANCE   (beside `voxmap serve`; defaults: voxmap default)
#include <voxmap.hpp>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <iostream>

int main(int argc, char** argv) {
  if (argc != 4) {
    std::cerr << "usage: driver PREFIX MAP DISTANCE\n";
    return 2;
  }
  const double distance = std::atof(argv[3]);
  const int w = 64, h = 48;
  try {
    voxmap::Publisher pub(argv[1], argv[2]);
    // To see the frame arrive: a publisher must outlive the service's receipt of its
    // frames (they live in its shared memory), so a one-shot driver waits for a snapshot.
    voxmap::Subscriber sub(argv[1], argv[2]);
    auto loan = pub.loan(w * h);
    // A pinhole camera looking along +x, 90 x 70 degrees: pixel (u, v) sees the wall at
    // (distance, -distance * tan(a), distance * tan(b)).
    for (int v = 0; v < h; ++v) {
      for (int u = 0; u < w; ++u) {
        float* p = loan[static_cast<std::size_t>(v * w + u)];
        double a = (u + 0.5) / w - 0.5, b = (v + 0.5) / h - 0.5;
        p[0] = static_cast<float>(distance);
        p[1] = static_cast<float>(-2.0 * distance * a * std::tan(0.785398));
        p[2] = static_cast<float>(2.0 * distance * b * std::tan(0.610865));
      }
    }
    auto now = std::chrono::system_clock::now().time_since_epoch();
    std::uint64_t stamp = static_cast<std::uint64_t>(std::chrono::duration_cast<std::chrono::nanoseconds>(now).count());
    std::uint64_t seq = loan.send({0.0, 0.0, 0.0}, {0.0, 0.0, 0.0, 1.0}, stamp);
    std::printf("sent frame %llu: %d points\n", static_cast<unsigned long long>(seq), w * h);
    auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    while (std::chrono::steady_clock::now() < deadline) {
      sub.wait(std::chrono::milliseconds(100));
      auto view = sub.latest();
      if (view && view->sequence() >= seq) {
        std::printf("in snapshot %llu\n", static_cast<unsigned long long>(view->sequence()));
        return 0;
      }
    }
    std::cerr << "the frame did not reach a snapshot in 10 s\n";
    return 1;
  } catch (const voxmap::Error& e) {
    std::cerr << "voxmap: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
