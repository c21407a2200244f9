/* c_checks SNAPSHOT MUTATIONS: the C API on null and bad arguments, then MUTATIONS views
 * opened from mutated copies of the snapshot file's bytes, each queried in every way. Any
 * crash fails the test; so does a wrong error code. Prints "ok N opened" at the end.
 * c_checks live PREFIX DIR: the publisher's and the control's calls against a running
 * service with a map (save into DIR, clear, load, refusals). Prints "ok live". */
#include <voxmap.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int failures = 0;
#define CHECK(cond)                                              \
  do {                                                           \
    if (!(cond)) {                                               \
      fprintf(stderr, "%s:%d: %s failed (last error: %s)\n",     \
              __FILE__, __LINE__, #cond, voxmap_last_error());   \
      failures++;                                                \
    }                                                            \
  } while (0)

static uint64_t rng = 0x9E3779B97F4A7C15ull;
static uint64_t next(void) {
  rng ^= rng << 13;
  rng ^= rng >> 7;
  rng ^= rng << 17;
  return rng;
}
static double uniform(double lo, double hi) { return lo + (hi - lo) * (double)(next() >> 11) / 9007199254740992.0; }

static void nulls(void) {
  const double a[3] = {0, 0, 0}, b[3] = {1, 1, 1};
  double out3[3];
  uint8_t st[4];
  uint64_t k;
  CHECK(voxmap_last_error() != NULL);
  CHECK(voxmap_view_open_file(NULL) == NULL && strstr(voxmap_last_error(), "null") != NULL);
  CHECK(voxmap_view_open_file("/nonexistent/map.vxm") == NULL && strlen(voxmap_last_error()) > 0);
  CHECK(voxmap_view_open_bytes(NULL, 10) == NULL);
  CHECK(voxmap_view_open_bytes((const uint8_t*)"VXMSNAP", 7) == NULL);
  CHECK(isnan(voxmap_view_resolution(NULL)));
  CHECK(voxmap_view_sequence(NULL) == 0);
  CHECK(voxmap_view_counts(NULL, &k, &k) == VOXMAP_ERR_NULL);
  CHECK(voxmap_view_bounds(NULL, out3, out3) == VOXMAP_ERR_NULL);
  CHECK(voxmap_view_state_at(NULL, 0, 0, 0) == VOXMAP_STATE_ERROR);
  memset(st, 0, sizeof st);
  voxmap_view_states_at(NULL, a, 1, st);
  CHECK(st[0] == VOXMAP_STATE_ERROR);
  voxmap_view_states_at(NULL, NULL, 4, NULL);
  CHECK(voxmap_view_first_hit(NULL, a, b, 0, out3) == VOXMAP_ERR_NULL);
  CHECK(voxmap_view_is_box_free(NULL, a, b, 0) == VOXMAP_ERR_NULL);
  CHECK(voxmap_view_probability_at(NULL, 0, 0, 0, out3) == VOXMAP_ERR_NULL);
  CHECK(voxmap_view_occupied(NULL) == NULL);
  CHECK(voxmap_occupied_next(NULL, out3, 1) == VOXMAP_ERR_NULL);
  voxmap_view_free(NULL);
  voxmap_occupied_free(NULL);
  CHECK(voxmap_subscriber_connect(NULL, "default") == NULL);
  CHECK(voxmap_subscriber_wait(NULL, 0) == VOXMAP_ERR_NULL);
  CHECK(voxmap_subscriber_latest(NULL, NULL) == VOXMAP_ERR_NULL);
  voxmap_subscriber_free(NULL);
  CHECK(voxmap_publisher_connect("voxmap", NULL) == NULL);
  CHECK(voxmap_publisher_loan(NULL, 10) == NULL);
  CHECK(voxmap_publisher_send(NULL, a, b, 0, NULL) == VOXMAP_ERR_NULL);
  CHECK(voxmap_publisher_discard(NULL) == VOXMAP_ERR_NULL);
  CHECK(voxmap_publisher_publish(NULL, NULL, 0, a, b, 0, NULL) == VOXMAP_ERR_NULL);
  voxmap_publisher_free(NULL);
  CHECK(voxmap_control_connect(NULL, NULL) == NULL);
  CHECK(voxmap_control_stats(NULL, NULL) == VOXMAP_ERR_NULL);
  CHECK(voxmap_control_save(NULL, "x") == VOXMAP_ERR_NULL);
  CHECK(voxmap_control_load(NULL, "x") == VOXMAP_ERR_NULL);
  CHECK(voxmap_control_clear(NULL) == VOXMAP_ERR_NULL);
  voxmap_control_free(NULL);
}

static void bad_arguments(const voxmap_view* v) {
  const double o[3] = {0, 0, 0}, nan3[3] = {NAN, 0, 0}, far[3] = {1e12, 0, 0};
  const double lo[3] = {1, 1, 1}, hi[3] = {0, 2, 2};
  double c[3];
  CHECK(voxmap_view_first_hit(v, nan3, o, 0, c) == VOXMAP_ERR_INVALID);
  CHECK(voxmap_view_first_hit(v, o, far, 0, c) == VOXMAP_ERR_INVALID);
  CHECK(voxmap_view_first_hit(v, o, NULL, 0, c) == VOXMAP_ERR_NULL);
  CHECK(voxmap_view_is_box_free(v, lo, hi, 1) == VOXMAP_ERR_INVALID);
  CHECK(voxmap_view_is_box_free(v, nan3, hi, 1) == VOXMAP_ERR_INVALID);
  CHECK(voxmap_view_state_at(v, NAN, 0, 0) == VOXMAP_UNKNOWN);
  CHECK(voxmap_view_bounds(v, NULL, c) == VOXMAP_ERR_NULL);
  CHECK(voxmap_view_probability_at(v, 0, 0, 0, NULL) == VOXMAP_ERR_NULL);
}

/* Every query on a view that opened; the answers are not checked, only that nothing
 * crashes and codes stay in range. */
static void exercise(const voxmap_view* v) {
  double xyz[3 * 64], a[3], b[3], c[3], p;
  uint8_t st[64];
  uint64_t k, o;
  for (int i = 0; i < 3 * 64; i++) xyz[i] = uniform(-8, 8);
  voxmap_view_states_at(v, xyz, 64, st);
  for (int i = 0; i < 64; i++) CHECK(st[i] <= VOXMAP_OCCUPIED);
  for (int i = 0; i < 8; i++) {
    for (int j = 0; j < 3; j++) {
      a[j] = uniform(-8, 8);
      b[j] = a[j] + uniform(0, 4);
    }
    int r = voxmap_view_first_hit(v, a, b, i & 1, c);
    CHECK(r >= 0 && r <= 1);
    r = voxmap_view_is_box_free(v, a, b, i & 1);
    CHECK(r >= 0 && r <= 1);
    r = voxmap_view_probability_at(v, a[0], a[1], a[2], &p);
    CHECK(r >= 0 && r <= 1);
    CHECK(voxmap_view_state_at(v, b[0], b[1], b[2]) <= VOXMAP_OCCUPIED);
  }
  CHECK(voxmap_view_counts(v, &k, &o) == 0);
  CHECK(voxmap_view_bounds(v, a, b) >= 0);
  voxmap_occupied* it = voxmap_view_occupied(v);
  CHECK(it != NULL);
  int64_t total = 0, n;
  while ((n = voxmap_occupied_next(it, xyz, 64)) > 0 && total < 1000000) total += n;
  CHECK(n >= 0);
  voxmap_occupied_free(it);
}

static uint64_t leaves(voxmap_control* c) {
  voxmap_stats s;
  memset(&s, 0, sizeof s);
  CHECK(voxmap_control_stats(c, &s) == 0);
  CHECK(strlen(s.kernel) > 0);
  return s.map_leaves;
}

static int live(const char* prefix, const char* dir) {
  voxmap_control* c = voxmap_control_connect(prefix, "default");
  voxmap_publisher* p = voxmap_publisher_connect(prefix, "default");
  CHECK(c != NULL && p != NULL);
  if (!c || !p) return 1;
  const double t[3] = {0, 0, 0}, q[4] = {0, 0, 0, 1}, zero_q[4] = {0, 0, 0, 0};
  /* One loan at a time; a bad pose keeps the loan; discard returns it. */
  float* pts = voxmap_publisher_loan(p, 10);
  CHECK(pts != NULL);
  CHECK(voxmap_publisher_loan(p, 10) == NULL && strstr(voxmap_last_error(), "already loaned") != NULL);
  CHECK(voxmap_publisher_send(p, t, zero_q, 0, NULL) == VOXMAP_ERR_INVALID);
  CHECK(voxmap_publisher_discard(p) == 0);
  CHECK(voxmap_publisher_send(p, t, q, 0, NULL) == VOXMAP_ERR_INVALID); /* nothing loaned */
  float xyz[3] = {1.5f, 0.0f, 0.0f};
  CHECK(voxmap_publisher_publish(p, xyz, 1, t, zero_q, 0, NULL) == VOXMAP_ERR_INVALID);
  /* Control: save, clear, load back; refusals are REJECTED with the service's reason. */
  uint64_t before = leaves(c);
  CHECK(before > 0);
  char path[4096];
  snprintf(path, sizeof path, "%s/c_saved.vxm", dir);
  CHECK(voxmap_control_save(c, path) == 0);
  CHECK(voxmap_control_clear(c) == 0);
  CHECK(leaves(c) == 0);
  CHECK(voxmap_control_load(c, path) == 0);
  CHECK(leaves(c) == before);
  CHECK(voxmap_control_load(c, "/nonexistent/map.vxm") == VOXMAP_ERR_REJECTED);
  CHECK(strlen(voxmap_last_error()) > 0);
  CHECK(leaves(c) == before);
  voxmap_view* v = voxmap_view_open_file(path);
  CHECK(v != NULL);
  uint64_t known = 0;
  CHECK(voxmap_view_counts(v, &known, NULL) == 0 && known > 0);
  voxmap_view_free(v);
  voxmap_publisher_free(p);
  voxmap_control_free(c);
  if (failures) return 1;
  printf("ok live\n");
  return 0;
}

int main(int argc, char** argv) {
  if (argc == 4 && strcmp(argv[1], "live") == 0) return live(argv[2], argv[3]);
  if (argc != 3) {
    fprintf(stderr, "usage: c_checks SNAPSHOT MUTATIONS\n");
    return 2;
  }
  nulls();
  FILE* f = fopen(argv[1], "rb");
  if (!f) return 2;
  fseek(f, 0, SEEK_END);
  long len = ftell(f);
  fseek(f, 0, SEEK_SET);
  uint8_t* good = malloc((size_t)len);
  uint8_t* bytes = malloc((size_t)len);
  if (!good || !bytes || fread(good, 1, (size_t)len, f) != (size_t)len) return 2;
  fclose(f);

  voxmap_view* v = voxmap_view_open_bytes(good, (size_t)len);
  CHECK(v != NULL);
  if (v) {
    bad_arguments(v);
    exercise(v);
    voxmap_view_free(v);
  }
  long mutations = atol(argv[2]), opened = 0;
  for (long m = 0; m < mutations; m++) {
    memcpy(bytes, good, (size_t)len);
    size_t n = (size_t)len;
    switch (next() % 4) {
      case 0: /* flip 1-8 random bytes */
        for (int i = (int)(next() % 8); i >= 0; i--) bytes[next() % n] ^= (uint8_t)(1 + next() % 255);
        break;
      case 1: /* a random 4- or 8-byte field, anywhere in the first 4 KiB (the header, the table) */
        {
          size_t at = next() % (n < 4096 ? n : 4096);
          uint64_t val = next() >> (next() % 64);
          memcpy(bytes + at, &val, at + 8 <= n ? 8 : n - at);
        }
        break;
      case 2: /* truncate */
        n = next() % n;
        break;
      default: /* overwrite a run with one value */
        {
          size_t at = next() % n, run = 1 + next() % 256;
          memset(bytes + at, (int)(next() & 0xff), at + run <= n ? run : n - at);
        }
        break;
    }
    voxmap_view* mv = voxmap_view_open_bytes(bytes, n);
    if (mv) {
      opened++;
      exercise(mv);
      voxmap_view_free(mv);
    } else {
      CHECK(strlen(voxmap_last_error()) > 0);
    }
  }
  free(good);
  free(bytes);
  if (failures) {
    fprintf(stderr, "%d checks failed\n", failures);
    return 1;
  }
  printf("ok %ld opened\n", opened);
  return 0;
}
