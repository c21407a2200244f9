// field SNAPSHOT POINTS OUT: the distance field queries of voxmap.hpp at every point of
// POINTS (a count, then x y z doubles) on the snapshot file SNAPSHOT, written to OUT in the
// layout tests/tests/foreign.rs expects from the Rust view.
#include <voxmap.hpp>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <vector>

namespace {

template <class T>
void put(std::vector<char>& out, const T& v) {
  const char* p = reinterpret_cast<const char*>(&v);
  out.insert(out.end(), p, p + sizeof v);
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 4) {
    std::cerr << "usage: field SNAPSHOT POINTS OUT\n";
    return 2;
  }
  try {
    auto view = voxmap::View::open_file(argv[1]);
    std::ifstream in(argv[2], std::ios::binary);
    std::uint64_t n = 0;
    in.read(reinterpret_cast<char*>(&n), sizeof n);
    std::vector<double> xyz(3 * n);
    in.read(reinterpret_cast<char*>(xyz.data()), static_cast<std::streamsize>(xyz.size() * sizeof(double)));
    if (!in) throw std::runtime_error("truncated points file");
    std::vector<char> out;
    put(out, view.field_max_distance());
    for (std::size_t i = 0; i < n; ++i) {
      voxmap::Vec3 p{xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]};
      auto d = view.distance_and_gradient_at(p);
      put(out, std::int32_t(d ? 1 : 0));
      put(out, d ? d->distance : 0.0);
      for (double g : d ? d->gradient : voxmap::Vec3{}) put(out, g);
      if (view.distance_at(p) != (d ? std::optional<double>(d->distance) : std::nullopt))
        throw std::runtime_error("distance_at differs from distance_and_gradient_at");
      double c[3] = {0, 0, 0}, dist = 0;
      std::int32_t code = voxmap_view_nearest_obstacle(view.get(), p.data(), c, &dist);
      put(out, code);
      for (double x : c) put(out, x);
      put(out, dist);
      auto near = view.nearest_obstacle(p);
      if (near.has_value() != (code == 1)) throw std::runtime_error("nearest_obstacle");
    }
    std::vector<double> dist(n), grad(3 * n);
    view.distances_at(xyz.data(), n, dist.data(), grad.data());
    for (std::size_t i = 0; i < n; ++i) {
      put(out, dist[i]);
      for (int k = 0; k < 3; ++k) put(out, grad[3 * i + k]);
    }
    std::ofstream o(argv[3], std::ios::binary);
    o.write(out.data(), static_cast<std::streamsize>(out.size()));
    return o ? 0 : 1;
  } catch (const voxmap::Error& e) {
    std::cerr << "voxmap error " << e.code() << ": " << e.what() << "\n";
    return 1;
  } catch (const std::exception& e) {
    std::cerr << e.what() << "\n";
    return 1;
  }
}
