// voxmap.hpp: the C++ API of voxmap, header-only over voxmap.h (C++17).
//
// RAII types over the C handles; failures throw voxmap::Error (with the C code and
// message), and "nothing there" is a std::optional. Batched queries take any contiguous
// container of points (std::vector<std::array<double, 3>>, std::vector<Eigen::Vector3d>,
// a C array) and write into a caller's buffer or return a vector. With VOXMAP_WITH_EIGEN
// defined (the CMake package defines it when it finds Eigen), Eigen overloads are added.
//
//   voxmap::Subscriber sub("voxmap", "default");
//   sub.wait(std::chrono::seconds(1));
//   if (auto view = sub.latest()) {
//     bool clear = !view->first_hit({0, 0, 1}, {5, 0, 1});
//     bool fits = view->is_box_free({-0.3, -0.3, 0.2}, {0.3, 0.3, 1.5});
//   }
//
// Thread safety is that of the C types (voxmap.h): views from files may be shared across
// threads; a Subscriber, Publisher or Control and the freeing of a subscriber's views
// belong to the thread that made them.
#ifndef VOXMAP_HPP
#define VOXMAP_HPP

#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "voxmap.h"

#ifdef VOXMAP_WITH_EIGEN
#include <Eigen/Core>
#endif

namespace voxmap {

/// A voxel's state.
enum class State : std::uint8_t {
  Unknown = VOXMAP_UNKNOWN,
  Free = VOXMAP_FREE,
  Occupied = VOXMAP_OCCUPIED,
};
static_assert(sizeof(State) == 1, "State is the C API's uint8_t code");

/// A point or vector in world metres.
using Vec3 = std::array<double, 3>;
static_assert(sizeof(Vec3) == 3 * sizeof(double), "Vec3 is three packed doubles");

/// A failed call: the C API's code (VOXMAP_ERR_*) and voxmap_last_error()'s message.
class Error : public std::runtime_error {
 public:
  Error(int code, const std::string& what) : std::runtime_error(what), code_(code) {}
  int code() const noexcept { return code_; }

 private:
  int code_;
};

namespace detail {
[[noreturn]] inline void fail(int code) { throw Error(code, voxmap_last_error()); }
inline int check(int r) {
  if (r < 0) fail(r);
  return r;
}
template <class T>
T* check_ptr(T* p) {
  if (p == nullptr) fail(VOXMAP_ERR_INVALID);
  return p;
}
inline const double* doubles(const Vec3* p) { return p->data(); }
#ifdef VOXMAP_WITH_EIGEN
static_assert(sizeof(Eigen::Vector3d) == 3 * sizeof(double), "Vector3d is three packed doubles");
inline const double* doubles(const Eigen::Vector3d* p) { return p->data(); }
#endif
}  // namespace detail

/// An axis-aligned box in world metres.
struct Box {
  Vec3 min;
  Vec3 max;
};

/// A validated snapshot, read in place: from a map or snapshot file, from bytes the caller
/// keeps alive, or from a Subscriber's shared memory. Move-only.
class View {
 public:
  /// Open a map file or snapshot file (verified whole).
  static View open_file(const std::string& path) {
    return View(detail::check_ptr(voxmap_view_open_file(path.c_str())));
  }
  /// Open snapshot bytes in place (no copy): they must outlive the view unchanged.
  static View open_bytes(const std::uint8_t* bytes, std::size_t len) {
    return View(detail::check_ptr(voxmap_view_open_bytes(bytes, len)));
  }
  /// Take ownership of a C view.
  explicit View(voxmap_view* v) noexcept : v_(v) {}
  View(View&& o) noexcept : v_(std::exchange(o.v_, nullptr)) {}
  View& operator=(View&& o) noexcept {
    if (this != &o) {
      voxmap_view_free(v_);
      v_ = std::exchange(o.v_, nullptr);
    }
    return *this;
  }
  View(const View&) = delete;
  View& operator=(const View&) = delete;
  ~View() { voxmap_view_free(v_); }

  /// The C handle (still owned by this object).
  const voxmap_view* get() const noexcept { return v_; }

  double resolution() const { return voxmap_view_resolution(v_); }
  /// The last frame the snapshot holds (0: none, or a file made from a map).
  std::uint64_t sequence() const { return voxmap_view_sequence(v_); }
  std::uint64_t timestamp_ns() const { return voxmap_view_timestamp_ns(v_); }
  /// (known, occupied) voxel counts.
  std::pair<std::uint64_t, std::uint64_t> counts() const {
    std::uint64_t k = 0, o = 0;
    detail::check(voxmap_view_counts(v_, &k, &o));
    return {k, o};
  }
  /// The box holding every known voxel; nothing when no voxel is known.
  std::optional<Box> bounds() const {
    Box b{};
    if (detail::check(voxmap_view_bounds(v_, b.min.data(), b.max.data())) == 0) return std::nullopt;
    return b;
  }

  /// The state of the voxel holding a point (not finite or outside the map's index space:
  /// unknown).
  State state_at(double x, double y, double z) const {
    std::uint8_t s = voxmap_view_state_at(v_, x, y, z);
    if (s == VOXMAP_STATE_ERROR) detail::fail(VOXMAP_ERR_NULL);
    return static_cast<State>(s);
  }
  State state_at(const Vec3& p) const { return state_at(p[0], p[1], p[2]); }

  /// States at n points (xyz: 3 n doubles) into out (n), in one batched call.
  void states_at(const double* xyz, std::size_t n, State* out) const {
    auto* codes = reinterpret_cast<std::uint8_t*>(out);
    voxmap_view_states_at(v_, xyz, n, codes);
    if (n > 0 && codes[0] == VOXMAP_STATE_ERROR) detail::fail(VOXMAP_ERR_NULL);
  }
  /// States at every point of a contiguous container (of Vec3, or of Eigen::Vector3d).
  template <class Points, class = decltype(detail::doubles(std::declval<const Points&>().data()))>
  std::vector<State> states_at(const Points& points) const {
    std::vector<State> out(points.size());
    if (!out.empty()) states_at(detail::doubles(points.data()), points.size(), out.data());
    return out;
  }

  /// The centre of the first occupied voxel on the segment from -> to (or unknown, with
  /// unknown_is_occupied); nothing when the line of sight is clear. Throws for an end
  /// point outside the index space or a segment over 65,536 voxels.
  std::optional<Vec3> first_hit(const Vec3& from, const Vec3& to,
                                bool unknown_is_occupied = false) const {
    Vec3 hit{};
    if (detail::check(voxmap_view_first_hit(v_, from.data(), to.data(), unknown_is_occupied,
                                            hit.data())) == 0)
      return std::nullopt;
    return hit;
  }

  /// Whether no voxel the box overlaps is occupied (nor unknown, unless unknown_is_free).
  /// Throws for an inverted box or a corner outside the index space.
  bool is_box_free(const Vec3& min, const Vec3& max, bool unknown_is_free = false) const {
    return detail::check(voxmap_view_is_box_free(v_, min.data(), max.data(), unknown_is_free)) == 1;
  }

  /// Occupancy probability of a known voxel, when the snapshot stores values.
  std::optional<double> probability_at(const Vec3& p) const {
    double q = 0;
    if (detail::check(voxmap_view_probability_at(v_, p[0], p[1], p[2], &q)) == 0) return std::nullopt;
    return q;
  }

  /// Whether the snapshot carries a distance field (a service run with --esdf).
  bool has_field() const { return detail::check(voxmap_view_field(v_, nullptr, nullptr)) == 1; }

  /// The field's max distance (metres): distances are capped there. Throws without a field.
  double field_max_distance() const {
    double d = 0;
    if (detail::check(voxmap_view_field(v_, &d, nullptr)) == 0)
      throw Error(VOXMAP_ERR_INVALID, "the snapshot carries no distance field");
    return d;
  }

  /// The distance (metres) to the nearest obstacle at p, interpolated between the voxel
  /// centres around it (their distances to the nearest 1/steps voxel, docs/distance-field.md)
  /// and capped at the max distance; nothing where the field does not reach (unknown space,
  /// outside its window). Throws without a field.
  std::optional<double> distance_at(const Vec3& p) const {
    double d = 0;
    if (detail::check(voxmap_view_distance_at(v_, p.data(), &d, nullptr)) == 0) return std::nullopt;
    return d;
  }

  /// A distance and its gradient (per metre, pointing away from the nearest obstacles).
  struct Distance {
    double distance;
    Vec3 gradient;
  };

  /// distance_at and its gradient.
  std::optional<Distance> distance_and_gradient_at(const Vec3& p) const {
    Distance r{};
    if (detail::check(voxmap_view_distance_at(v_, p.data(), &r.distance, r.gradient.data())) == 0)
      return std::nullopt;
    return r;
  }

  /// The centre of the obstacle voxel nearest to the voxel holding p; nothing when none
  /// lies within the max distance or the field does not reach p (tell them apart with
  /// distance_at). Throws without a field.
  std::optional<Vec3> nearest_obstacle(const Vec3& p) const {
    Vec3 c{};
    if (detail::check(voxmap_view_nearest_obstacle(v_, p.data(), c.data(), nullptr)) != 1) return std::nullopt;
    return c;
  }

  /// distance_at at n points (x, y, z each): distance[i], NaN where the field does not
  /// reach; gradient (3 n doubles) may be null. One call for a whole trajectory.
  void distances_at(const double* xyz, std::size_t n, double* distance, double* gradient = nullptr) const {
    detail::check(voxmap_view_distances_at(v_, xyz, n, distance, gradient));
  }

  /// distances_at over a contiguous container of points (Vec3 or Eigen::Vector3d).
  template <class Points, class = decltype(detail::doubles(std::declval<const Points&>().data()))>
  std::vector<double> distances_at(const Points& points) const {
    std::vector<double> out(points.size());
    if (!out.empty()) distances_at(detail::doubles(points.data()), points.size(), out.data());
    return out;
  }

  /// Call f(const Vec3& centre) for each occupied voxel, in chunks read into a buffer.
  template <class F>
  void for_each_occupied(F&& f) const {
    voxmap_occupied* it = detail::check_ptr(voxmap_view_occupied(v_));
    std::vector<Vec3> buf(4096);
    try {
      for (;;) {
        std::int64_t n = voxmap_occupied_next(it, buf[0].data(), buf.size());
        if (n < 0) detail::fail(static_cast<int>(n));
        if (n == 0) break;
        for (std::int64_t i = 0; i < n; ++i) f(buf[static_cast<std::size_t>(i)]);
      }
    } catch (...) {
      voxmap_occupied_free(it);
      throw;
    }
    voxmap_occupied_free(it);
  }
  /// Every occupied voxel's centre.
  std::vector<Vec3> occupied_centres() const {
    std::vector<Vec3> out;
    for_each_occupied([&](const Vec3& c) { out.push_back(c); });
    return out;
  }

#ifdef VOXMAP_WITH_EIGEN
  // Templates over Eigen expressions, so that braced points ({x, y, z}) stay Vec3.
  template <class D>
  State state_at(const Eigen::MatrixBase<D>& p) const {
    return state_at(p(0), p(1), p(2));
  }
  template <class D1, class D2>
  std::optional<Eigen::Vector3d> first_hit(const Eigen::MatrixBase<D1>& from,
                                           const Eigen::MatrixBase<D2>& to,
                                           bool unknown_is_occupied = false) const {
    auto h = first_hit(Vec3{from(0), from(1), from(2)}, Vec3{to(0), to(1), to(2)}, unknown_is_occupied);
    if (!h) return std::nullopt;
    return Eigen::Vector3d((*h)[0], (*h)[1], (*h)[2]);
  }
  template <class D1, class D2>
  bool is_box_free(const Eigen::MatrixBase<D1>& min, const Eigen::MatrixBase<D2>& max,
                   bool unknown_is_free = false) const {
    return is_box_free(Vec3{min(0), min(1), min(2)}, Vec3{max(0), max(1), max(2)}, unknown_is_free);
  }
  /// States at the rows of an N x 3 row-major matrix.
  std::vector<State> states_at(
      const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>>& xyz) const {
    std::vector<State> out(static_cast<std::size_t>(xyz.rows()));
    if (!out.empty()) states_at(xyz.data(), out.size(), out.data());
    return out;
  }
#endif

 private:
  voxmap_view* v_;
};

/// A planner's connection to the snapshots of one map. Move-only; one thread.
class Subscriber {
 public:
  Subscriber(const std::string& prefix, const std::string& map)
      : s_(detail::check_ptr(voxmap_subscriber_connect(prefix.c_str(), map.c_str()))) {}
  Subscriber(Subscriber&& o) noexcept : s_(std::exchange(o.s_, nullptr)) {}
  Subscriber& operator=(Subscriber&& o) noexcept {
    if (this != &o) {
      voxmap_subscriber_free(s_);
      s_ = std::exchange(o.s_, nullptr);
    }
    return *this;
  }
  Subscriber(const Subscriber&) = delete;
  Subscriber& operator=(const Subscriber&) = delete;
  ~Subscriber() { voxmap_subscriber_free(s_); }

  /// Wait for a snapshot newer than the last received; true if one came in time.
  bool wait(std::chrono::milliseconds timeout) {
    return detail::check(voxmap_subscriber_wait(s_, static_cast<std::uint64_t>(timeout.count()))) == 1;
  }
  /// The newest snapshot, in place in shared memory; valid until the View is destroyed
  /// (hold at most one besides the newest).
  std::optional<View> latest() {
    voxmap_view* v = nullptr;
    if (detail::check(voxmap_subscriber_latest(s_, &v)) == 0) return std::nullopt;
    return View(v);
  }

 private:
  voxmap_subscriber* s_;
};

class Publisher;

/// Points loaned in shared memory: write them, then send(). Destroyed unsent, the memory
/// goes back.
class Loan {
 public:
  Loan(Loan&& o) noexcept : p_(std::exchange(o.p_, nullptr)), data_(o.data_), n_(o.n_) {}
  Loan(const Loan&) = delete;
  Loan& operator=(const Loan&) = delete;
  Loan& operator=(Loan&&) = delete;
  ~Loan() {
    if (p_ != nullptr) voxmap_publisher_discard(p_);
  }
  /// Point i (x, y, z in the sensor frame, metres).
  float* operator[](std::size_t i) { return data_ + 3 * i; }
  /// The 3 n floats.
  float* data() { return data_; }
  std::size_t size() const { return n_; }
  /// Send with the sensor's pose in the map frame and the time stamp (ns); returns the
  /// frame's sequence number.
  std::uint64_t send(const Vec3& translation, const std::array<double, 4>& rotation_xyzw,
                     std::uint64_t stamp_ns) {
    if (p_ == nullptr) throw Error(VOXMAP_ERR_INVALID, "the loan was already sent");
    std::uint64_t seq = 0;
    detail::check(voxmap_publisher_send(p_, translation.data(), rotation_xyzw.data(), stamp_ns, &seq));
    p_ = nullptr;
    return seq;
  }

 private:
  friend class Publisher;
  Loan(voxmap_publisher* p, float* data, std::size_t n) : p_(p), data_(data), n_(n) {}
  voxmap_publisher* p_;
  float* data_;
  std::size_t n_;
};

/// A sensor driver's connection to the frames of one map. Move-only; one thread.
class Publisher {
 public:
  Publisher(const std::string& prefix, const std::string& map)
      : p_(detail::check_ptr(voxmap_publisher_connect(prefix.c_str(), map.c_str()))) {}
  Publisher(Publisher&& o) noexcept : p_(std::exchange(o.p_, nullptr)) {}
  Publisher(const Publisher&) = delete;
  Publisher& operator=(const Publisher&) = delete;
  Publisher& operator=(Publisher&&) = delete;
  ~Publisher() { voxmap_publisher_free(p_); }

  /// Loan shared memory for n points (zeroed); one loan at a time.
  Loan loan(std::size_t n) { return Loan(p_, detail::check_ptr(voxmap_publisher_loan(p_, n)), n); }
  /// Copy n points (xyz: 3 n floats) into a loan and send them.
  std::uint64_t publish(const float* xyz, std::size_t n, const Vec3& translation,
                        const std::array<double, 4>& rotation_xyzw, std::uint64_t stamp_ns) {
    std::uint64_t seq = 0;
    detail::check(voxmap_publisher_publish(p_, xyz, n, translation.data(), rotation_xyzw.data(),
                                           stamp_ns, &seq));
    return seq;
  }

 private:
  voxmap_publisher* p_;
};

/// Requests to a running service. Move-only; one thread.
class Control {
 public:
  Control(const std::string& prefix, const std::string& map)
      : c_(detail::check_ptr(voxmap_control_connect(prefix.c_str(), map.c_str()))) {}
  Control(Control&& o) noexcept : c_(std::exchange(o.c_, nullptr)) {}
  Control(const Control&) = delete;
  Control& operator=(const Control&) = delete;
  Control& operator=(Control&&) = delete;
  ~Control() { voxmap_control_free(c_); }

  void set_timeout(std::chrono::milliseconds t) {
    detail::check(voxmap_control_set_timeout_ms(c_, static_cast<std::uint64_t>(t.count())));
  }
  voxmap_stats stats() const {
    voxmap_stats s{};
    detail::check(voxmap_control_stats(c_, &s));
    return s;
  }
  void save(const std::string& path) const { detail::check(voxmap_control_save(c_, path.c_str())); }
  void load(const std::string& path) const { detail::check(voxmap_control_load(c_, path.c_str())); }
  void clear() const { detail::check(voxmap_control_clear(c_)); }

 private:
  voxmap_control* c_;
};

}  // namespace voxmap

#endif  // VOXMAP_HPP
