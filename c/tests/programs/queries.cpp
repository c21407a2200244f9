// queries MAP QUERIES OUT: answer every query of QUERIES (see tests/tests/foreign.rs for the
// layout) on the map or snapshot file MAP through voxmap.hpp, and write the answers to OUT.
#include <voxmap.hpp>

#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <vector>

namespace {

std::vector<double> read_block(std::ifstream& in, std::size_t per) {
  std::uint64_t n = 0;
  in.read(reinterpret_cast<char*>(&n), sizeof n);
  std::vector<double> v(n * per);
  in.read(reinterpret_cast<char*>(v.data()), static_cast<std::streamsize>(v.size() * sizeof(double)));
  if (!in) throw std::runtime_error("truncated queries file");
  return v;
}

template <class T>
void put(std::vector<char>& out, const T& v) {
  const char* p = reinterpret_cast<const char*>(&v);
  out.insert(out.end(), p, p + sizeof v);
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 4) {
    std::cerr << "usage: queries MAP QUERIES OUT\n";
    return 2;
  }
  try {
    auto view = voxmap::View::open_file(argv[1]);
    std::ifstream in(argv[2], std::ios::binary);
    auto points = read_block(in, 3);
    auto rays = read_block(in, 7);
    auto boxes = read_block(in, 7);
    std::size_t np = points.size() / 3;

    std::vector<char> out;
    put(out, view.resolution());
    auto [known, occupied] = view.counts();
    put(out, known);
    put(out, occupied);
    auto b = view.bounds();
    put(out, std::int32_t(b ? 1 : 0));
    for (double c : b ? b->min : voxmap::Vec3{}) put(out, c);
    for (double c : b ? b->max : voxmap::Vec3{}) put(out, c);

    std::vector<voxmap::State> batched(np);
    view.states_at(points.data(), np, batched.data());
    for (auto s : batched) put(out, static_cast<std::uint8_t>(s));
    for (std::size_t i = 0; i < np; ++i)
      put(out, static_cast<std::uint8_t>(view.state_at(points[3 * i], points[3 * i + 1], points[3 * i + 2])));
    for (std::size_t i = 0; i < np; ++i) {
      auto p = view.probability_at({points[3 * i], points[3 * i + 1], points[3 * i + 2]});
      put(out, std::int32_t(p ? 1 : 0));
      put(out, p ? *p : 0.0);
    }
    for (std::size_t i = 0; i < rays.size() / 7; ++i) {
      const double* r = &rays[7 * i];
      std::int32_t code;
      voxmap::Vec3 c{};
      try {
        auto hit = view.first_hit({r[0], r[1], r[2]}, {r[3], r[4], r[5]}, r[6] != 0);
        code = hit ? 1 : 0;
        if (hit) c = *hit;
      } catch (const voxmap::Error& e) {
        code = e.code();
      }
      put(out, code);
      for (double x : c) put(out, x);
    }
    for (std::size_t i = 0; i < boxes.size() / 7; ++i) {
      const double* r = &boxes[7 * i];
      std::int32_t code;
      try {
        code = view.is_box_free({r[0], r[1], r[2]}, {r[3], r[4], r[5]}, r[6] != 0) ? 1 : 0;
      } catch (const voxmap::Error& e) {
        code = e.code();
      }
      put(out, code);
    }
    std::uint64_t n = 0;
    voxmap::Vec3 sum{};
    view.for_each_occupied([&](const voxmap::Vec3& c) {
      ++n;
      for (int k = 0; k < 3; ++k) sum[k] += c[k];
    });
    put(out, n);
    for (double x : sum) put(out, x);

    std::ofstream o(argv[3], std::ios::binary);
    o.write(out.data(), static_cast<std::streamsize>(out.size()));
    return o ? 0 : 1;
  } catch (const voxmap::Error& e) {
    std::cerr << "voxmap error " << e.code() << ": " << e.what() << "\n";
    return 1;
  }
}
