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
#ifdef VOXMAP_WITH_EIGEN
    // The Eigen overloads answer as the array ones.
    for (std::size_t i = 0; i + 1 < np && i < 200; i += 2) {
      Eigen::Vector3d a(points[3 * i], points[3 * i + 1], points[3 * i + 2]);
      Eigen::Vector3d b(points[3 * i + 3], points[3 * i + 4], points[3 * i + 5]);
      if (view.state_at(a) != view.state_at(a.x(), a.y(), a.z())) throw std::runtime_error("Eigen state_at");
      if (!a.allFinite() || !b.allFinite()) continue;
      auto h1 = view.first_hit(a, b);
      auto h2 = view.first_hit(voxmap::Vec3{a.x(), a.y(), a.z()}, voxmap::Vec3{b.x(), b.y(), b.z()});
      if (h1.has_value() != h2.has_value() || (h1 && ((*h1)(0) != (*h2)[0] || (*h1)(2) != (*h2)[2])))
        throw std::runtime_error("Eigen first_hit");
      Eigen::Vector3d lo = a.cwiseMin(b), hi = a.cwiseMax(b);
      if (view.is_box_free(lo, hi, true) != view.is_box_free({lo.x(), lo.y(), lo.z()}, {hi.x(), hi.y(), hi.z()}, true))
        throw std::runtime_error("Eigen is_box_free");
    }
    {
      Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor> m(np, 3);
      for (std::size_t i = 0; i < np; ++i) m.row(static_cast<Eigen::Index>(i)) << points[3 * i], points[3 * i + 1], points[3 * i + 2];
      if (view.states_at(m) != batched) throw std::runtime_error("Eigen states_at");
      std::vector<Eigen::Vector3d> vs;
      for (std::size_t i = 0; i < np; ++i) vs.emplace_back(points[3 * i], points[3 * i + 1], points[3 * i + 2]);
      if (view.states_at(vs) != batched) throw std::runtime_error("Eigen vector states_at");
    }
    std::printf("eigen overloads checked\n");
#endif
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
  } catch (const std::exception& e) {
    std::cerr << e.what() << "\n";
    return 1;
  }
}
