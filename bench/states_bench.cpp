// The C side of bench/bindings_vs_rust.sh: ns per point of voxmap_view_states_at on a
// snapshot file, over the points of a file (f64 x, y, z), in batches, median of REPS.
//   states_bench SNAPSHOT POINTS BATCH REPS
#include <voxmap.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <vector>

int main(int argc, char** argv) {
  if (argc != 5) {
    std::fprintf(stderr, "usage: states_bench SNAPSHOT POINTS BATCH REPS\n");
    return 2;
  }
  voxmap_view* v = voxmap_view_open_file(argv[1]);
  if (!v) {
    std::fprintf(stderr, "%s\n", voxmap_last_error());
    return 1;
  }
  std::ifstream in(argv[2], std::ios::binary);
  std::vector<char> raw((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  std::vector<double> xyz(raw.size() / 8);
  std::copy(raw.begin(), raw.begin() + xyz.size() * 8, reinterpret_cast<char*>(xyz.data()));
  std::size_t n = xyz.size() / 3, batch = std::strtoul(argv[3], nullptr, 10);
  int reps = std::atoi(argv[4]);
  std::vector<std::uint8_t> out(batch);
  std::vector<double> per;
  std::size_t occupied = 0;
  for (int r = 0; r < reps; ++r) {
    auto t = std::chrono::steady_clock::now();
    for (std::size_t i = 0; i < n; i += batch) {
      std::size_t m = std::min(batch, n - i);
      voxmap_view_states_at(v, xyz.data() + 3 * i, m, out.data());
      for (std::size_t k = 0; k < m; ++k) occupied += out[k] == VOXMAP_OCCUPIED;
    }
    per.push_back(std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - t).count() / n);
  }
  std::sort(per.begin(), per.end());
  std::printf("c voxmap_view_states_at: %.1f ns/point (median of %d, batch %zu, %zu points; %zu occupied answers)\n",
              per[per.size() / 2], reps, batch, n, occupied);
  voxmap_view_free(v);
  return 0;
}
