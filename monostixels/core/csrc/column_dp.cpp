// Fused hard column DP of the mono-stixel solver (tau == 0): the C++ twin of the eager stage
// loop in monostixels/core/columns.py and solver.py (`_flow_prefix` + the loop of `solve_columns`).
//
// Why it exists: the eager loop runs ~100 torch ops per DP stage over (columns x hypotheses x
// types); it is bound by op overhead and memory traffic. Here one column is solved start to
// end in cache-sized buffers, columns in parallel (at::parallel_for, i.e. torch's intra-op
// threads, so torch.set_num_threads governs it; columns are handed out in chunks of kChunk).
//
// Exactness: every floating-point expression is written in the same order as the torch ops of
// the eager path, compiled without contraction (-ffp-contract=off) and without fast-math
// (-fno-trapping-math only lets the compiler if-convert and vectorise; it changes no value), and
// prefix sums accumulate in double like torch.cumsum on the CPU. Minima keep the first index on
// ties, like torch.min. The result is bit-identical to the eager path (tests/test_solver_fast.py).
//
// Work saved against the eager formulation, none of which changes a value:
// - Repeated hypotheses (bit-identical inverse depths: the reference ground and the farthest
//   depth fill every cell without a valid fit, typically 40-65 % of a column's ground and static
//   sets) are solved once. Every cost of a copy equals its original's, and the original has the
//   lower flat index, so torch.min would pick the original: the first occurrences decide alone.
// - Hypothesis loops run over whole vectors of kLanes (copies of a real hypothesis pad the sets;
//   their open segments are held at +inf, so they never win).
// - The minimum over (hypothesis, class) keeps one running (value, hypothesis) pair per class
//   and lane and resolves the eager flatten order (hypothesis-major, first index on ties) once
//   per stage, instead of a compare-and-blend chain through every element.
//
// Layout: all inputs are contiguous, of one floating dtype (float32 or float64); C columns,
// n cells (cell 0 at the image bottom), Kg / Ko / Kd hypotheses of ground / object / dynamic.
//
// column_dp follows the back-pointers of each column as well (solver._backtrack) and returns the
// stixel table: the DP's state never leaves the thread's buffers. The file also holds the
// solver's preparation for this path, each the twin of its torch code with the same bits: cell
// means with the input value checks (cell_sums), per-cell geometry (geometry), hypothesis sets
// (hypotheses) and semantic prefix sums (semantic_prefix).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <tuple>
#include <type_traits>
#include <utility>
#include <vector>

namespace {

constexpr int kTypes = 4;  // ground, static object, dynamic object, sky
constexpr int64_t kChunk = 2;  // columns a thread takes at a time
constexpr int kMaxClasses = 3;  // classes per type (solver: TYPE_CLASSES; cls_table has 3 slots)
constexpr int64_t kCovEntries = 4;  // a 2 x 2 flow covariance per pixel
constexpr int kGround = 0, kStatic = 1, kDynamic = 2, kSky = 3;
inline bool is_object(int j) { return j == kStatic || j == kDynamic; }

// Vectors of one register of the target (GCC/Clang vector extension): 64 bytes with AVX-512 (16
// floats or 8 doubles), 32 with AVX (AVX2, x86-64-v3), else 16, with integers of the same width
// (hypothesis / bottom indices) so that comparison masks of values and indices have one type.
// Never wider than the target's registers: gcc expands an operation on a wider vector piecewise,
// through the stack, and a 64-byte build for AVX2 ran 7x slower (docs/experiments.md, "Every x86
// CPU"). The lane count changes no value: padding lanes hold +inf and ties go to the lowest
// flat index whatever the width.
#if defined(__AVX512F__)
constexpr int kVecBytes = 64;
#elif defined(__AVX__)
constexpr int kVecBytes = 32;
#else
constexpr int kVecBytes = 16;
#endif
template <typename T>
struct Simd;
template <>
struct Simd<float> {
  using I = int32_t;
  typedef float V __attribute__((vector_size(kVecBytes)));
  typedef int32_t VI __attribute__((vector_size(kVecBytes)));
  typedef int8_t VB __attribute__((vector_size(kVecBytes / 4)));
};
template <>
struct Simd<double> {
  using I = int64_t;
  typedef double V __attribute__((vector_size(kVecBytes)));
  typedef int64_t VI __attribute__((vector_size(kVecBytes)));
  typedef int8_t VB __attribute__((vector_size(kVecBytes / 8)));
};
template <typename T>
constexpr int64_t kLanes = kVecBytes / static_cast<int64_t>(sizeof(T));

template <typename Vec>
inline Vec load(const void* p) {
  Vec v;
  std::memcpy(&v, p, sizeof(Vec));
  return v;
}
template <typename Vec>
inline void store(void* p, const Vec& v) {
  std::memcpy(p, &v, sizeof(Vec));
}
// Every lane = s (s - 0 is s bit for bit, -0 and inf included; the compiler emits a broadcast).
template <typename Vec, typename S>
inline Vec splat(S s) {
  using E = typename std::remove_reference<decltype(Vec{}[0])>::type;
  return static_cast<E>(s) - Vec{};
}
template <typename Vec>
inline Vec iota() {
  Vec v;
  for (size_t l = 0; l < sizeof(Vec) / sizeof(v[0]); ++l) v[l] = l;
  return v;
}
inline int64_t round_up(int64_t x, int64_t m) { return (x + m - 1) / m * m; }

// Lanes rotated by H: lane l gets lane (l + H) mod N.
template <int H, typename Vec, size_t... Is>
inline Vec rotate(const Vec& a, std::index_sequence<Is...>) {
  return __builtin_shufflevector(a, a, ((Is + H) % sizeof...(Is))...);
}

// Every lane = the minimum over the lanes, by halving.
template <int H, typename Vec>
inline Vec min_lanes(Vec v) {
  constexpr size_t N = sizeof(Vec) / sizeof(v[0]);
  const Vec v2 = rotate<H>(v, std::make_index_sequence<N>{});
  v = v2 < v ? v2 : v;
  if constexpr (H > 1) return min_lanes<H / 2>(v);
  return v;
}

// x made contiguous, after checking that it has ref's dtype (each op takes one floating dtype).
inline at::Tensor contiguous_as(const at::Tensor& x, const at::Tensor& ref, const char* op, const char* name) {
  TORCH_CHECK(x.scalar_type() == ref.scalar_type(), op, ": ", name, " has dtype ", x.scalar_type(), ", expected ",
              ref.scalar_type());
  return x.contiguous();
}

// Prior parameters, in the order of `_PARAM_ORDER` in monostixels/core/_dp_cpp.py.
template <typename T>
struct Params {
  T beta_mc, a_gb, b_gb, a_ga, b_ga, a_ord, b_ord, a_flat, b_flat, alpha_F, delta_F, alpha_dyn;
  T p_min, p_max, grav_tol, z_min;
};

// Ψ_str of an object with depth 1/inv_p above predecessor type j (energy.gravity and
// energy.ordering_from_depths, combined as in solver._structural_object). q_inv_p = q * inv_p.
// Scalars or vectors of T alike.
template <typename T, typename X>
inline X structural(const Params<T>& P, X inv_p, X q_inv_p, T inv_pp, T inv_gp, int j) {
  const X dh = inv_gp - q_inv_p;
  const X grav = (dh < -P.grav_tol) ? P.a_gb + P.b_gb * (-dh) : P.a_ga + P.b_ga * dh;
  if (!is_object(j)) return grav;
  const X d = inv_pp - inv_p;
  const X ord = (d > T(0)) ? P.a_ord + P.b_ord * d : X{} + T(0);
  return ord < grav ? ord : grav;  // torch.minimum (no NaN here)
}

// Per-cell inputs of the flow cost of one column (columns._row_costs).
template <typename T>
struct Cell {
  T up, vp, c00, c01x2, c11, logdet, rows, a0, a1, a2, sg, so;
};

// Robust flow cost of one cell for predicted point (h0, h1, h2), weighted by rows (columns._row_costs).
template <typename T>
inline T row_cost(const Params<T>& P, const Cell<T>& c, T h0, T h1, T h2) {
  const bool ok = h2 > P.z_min;
  const T zs = ok ? h2 : T(1);
  const T rx = c.up - h0 / zs;
  const T ry = c.vp - h1 / zs;
  const T q = c.c00 * rx * rx + c.c01x2 * rx * ry + c.c11 * ry * ry;
  T v = c.logdet + T(0.5) * q;
  v = (P.alpha_F < v) ? P.alpha_F : v;  // torch.minimum(v, alpha_F)
  if (!ok) v = P.alpha_F;
  return v * c.rows * P.delta_F;
}

// Prefix-summed flow cost of one type's hypotheses over one column's cells, (n + 1) x K,
// cell-major (columns._flow_prefix). Double accumulators like torch.cumsum on the CPU. The inner
// loops over hypotheses are branch-free so that the compiler vectorises them.
template <typename T, int Type>
void flow_prefix(const Params<T>& P, const std::vector<Cell<T>>& cells, int64_t K, const T* hyp, T cK0, T cK1,
                 T cK2, double* acc, T* Pt) {
  const int64_t n = static_cast<int64_t>(cells.size());
  const T imp = P.alpha_F * P.delta_F;  // cost per row of a cell where the type cannot be seen
  for (int64_t k = 0; k < K; ++k) { acc[k] = 0.0; Pt[k] = T(0); }
  for (int64_t j = 0; j < n; ++j) {
    const Cell<T> c = cells[j];
    T* row = Pt + (j + 1) * K;
    const bool impossible = (Type == kGround && c.sg <= T(0)) || (Type == kSky && c.sg > T(0));
    if (impossible) {  // ground above / sky below the horizon (columns.beyond_horizon)
      const double cost = static_cast<double>(imp * c.rows);
      for (int64_t k = 0; k < K; ++k) { acc[k] += cost; row[k] = static_cast<T>(acc[k]); }
      continue;
    }
    for (int64_t k = 0; k < K; ++k) {
      T h0, h1, h2;
      if (Type == kDynamic) {
        const T* g = hyp + k * 3;
        h0 = c.a0 + c.so * g[0];
        h1 = c.a1 + c.so * g[1];
        h2 = c.a2 + c.so * g[2];
      } else if (Type == kSky) {
        h0 = c.a0;
        h1 = c.a1;
        h2 = c.a2;
      } else {
        const T ps = hyp[k] * (Type == kGround ? c.sg : c.so);
        h0 = c.a0 + ps * cK0;
        h1 = c.a1 + ps * cK1;
        h2 = c.a2 + ps * cK2;
      }
      T cost = row_cost(P, c, h0, h1, h2);
      if (Type == kDynamic) cost = cost + P.alpha_dyn * c.rows;
      acc[k] += static_cast<double>(cost);
      row[k] = static_cast<T>(acc[k]);
    }
  }
}

// G = min_j Ep[j] + st(j) and kb = the first j attaining it (torch.min semantics): types in
// ascending order with a strict "<", starting from +inf / 0. Unreachable predecessors (Ep = inf)
// never win a strict minimum and are skipped. For the types whose prior does not depend on the
// hypothesis.
template <typename T, typename St>
inline void best_predecessor(const T* Ep, T& G, int32_t& kb, St&& st) {
  const T inf = std::numeric_limits<T>::infinity();
  G = inf;
  kb = 0;
  for (int j = 0; j < kTypes; ++j) {
    if (!(Ep[j] < inf)) continue;
    const T cand = Ep[j] + st(j);
    if (cand < G) { G = cand; kb = j; }
  }
}

// Indices of the first occurrence of every distinct value of x[0..K) (bit patterns), ascending.
// `table` is scratch for an open-addressing hash set of indices + 1 (0 = empty).
template <typename T>
int64_t first_occurrences(const T* x, int64_t K, std::vector<int32_t>& table, int32_t* keep) {
  using U = typename std::conditional<sizeof(T) == 4, uint32_t, uint64_t>::type;
  int bits = 1;
  while ((int64_t{1} << bits) < 2 * K) ++bits;
  const int64_t cap = int64_t{1} << bits;
  table.assign(cap, 0);
  int64_t m = 0;
  for (int64_t k = 0; k < K; ++k) {
    U key;
    std::memcpy(&key, x + k, sizeof(T));
    uint64_t h = (static_cast<uint64_t>(key) * 0x9E3779B97F4A7C15ull) >> (64 - bits);
    for (;; h = (h + 1) & (cap - 1)) {
      const int32_t e = table[h];
      if (e == 0) {
        table[h] = static_cast<int32_t>(k + 1);
        keep[m++] = static_cast<int32_t>(k);
        break;
      }
      if (std::memcmp(x + (e - 1), x + k, sizeof(T)) == 0) break;  // a copy of an earlier one
    }
  }
  return m;
}

// One type's DP stage for NC classes: update the running minimum over segment bottoms per
// (class, hypothesis) with the segments that start at cell i (gk = G - P0: best predecessor
// minus the prefix at i), close all open segments at cell i with the prefix sums at i + 1, and
// return the minimum `val` and its first (hypothesis-major) index (h, c), as torch.min over the
// eager flatten would. Kp is a multiple of the lane count; gk is +inf on padding hypotheses.
template <typename T, int NC>
inline void close_segments(int64_t Kp, const T* gk, const T* P1, T* MH, typename Simd<T>::I* MB, const T* L0,
                           const T* L1, typename Simd<T>::I ii, T& val, int64_t& h, int64_t& c) {
  using V = typename Simd<T>::V;
  using VI = typename Simd<T>::VI;
  using I = typename Simd<T>::I;
  constexpr int64_t L = kLanes<T>;
  const V vinf = splat<V>(std::numeric_limits<T>::infinity());
  const VI iiv = splat<VI>(ii);
  V best[NC];
  VI bk[NC];
  VI kv = iota<VI>();
  for (int cc = 0; cc < NC; ++cc) { best[cc] = vinf; bk[cc] = kv; }
  for (int64_t k = 0; k < Kp; k += L) {
    const V g = load<V>(gk + k), p1 = load<V>(P1 + k);
    for (int cc = 0; cc < NC; ++cc) {
      T* mh = MH + cc * Kp + k;
      I* mb = MB + cc * Kp + k;
      V m = load<V>(mh);
      VI b = load<VI>(mb);
      const V cH = g - L0[cc];
      const VI lt = cH < m;
      m = lt ? cH : m;
      b = lt ? iiv : b;
      store(mh, m);
      store(mb, b);
      const V tot = m + (p1 + L1[cc]);
      // Per (class, lane) the hypotheses come in ascending order: a strict "<" keeps the first.
      const VI bt = tot < best[cc];
      best[cc] = bt ? tot : best[cc];
      bk[cc] = bt ? kv : bk[cc];
    }
    kv += static_cast<I>(L);
  }
  // Per lane the first (value, flat index) over the classes, then over the lanes: the minimum
  // value, and the lowest flat index among the lanes that hold it.
  V v = best[0];
  VI f = bk[0] * static_cast<I>(NC);
  for (int cc = 1; cc < NC; ++cc) {
    const VI fc = bk[cc] * static_cast<I>(NC) + static_cast<I>(cc);
    const VI better = (best[cc] < v) | ((best[cc] == v) & (fc < f));
    v = better ? best[cc] : v;
    f = better ? fc : f;
  }
  const V vm = min_lanes<static_cast<int>(L / 2)>(v);
  const VI fm = min_lanes<static_cast<int>(L / 2)>(vm == v ? f : splat<VI>(std::numeric_limits<I>::max()));
  val = vm[0];
  h = fm[0] / NC;
  c = fm[0] % NC;
}

// One stixel of the solution (solver.ColumnSolution's fields).
template <typename T>
struct Stixel {
  int64_t col, b, t, type, cls;
  T p, p_ground, tau0, tau1, cost;
};

template <typename T>
void solve_columns(std::atomic<int64_t>& next, int64_t C, int64_t n, int64_t Kg, int64_t Ko, int64_t Kd, int64_t ncl,
                 const Params<T>& P, const T* a, const T* cK, const T* s_g, const T* s_o, const T* u,
                 const T* v, const T* rows, const T* flow, const T* cov_inv, const T* logdet,
                 const T* p_ground, const T* p_object, const T* g_dyn, const T* tau, const T* Lp,
                 const T* q, const T* p_ref, const bool* degenerate, const int64_t* cls_table,
                 const int64_t* ncs, bool has_sem, T* energy, std::vector<Stixel<T>>& out) {
  using V = typename Simd<T>::V;
  using VI = typename Simd<T>::VI;
  using VB = typename Simd<T>::VB;
  using I = typename Simd<T>::I;
  constexpr int64_t L = kLanes<T>;
  const T inf = std::numeric_limits<T>::infinity();
  const V vinf = splat<V>(inf);
  // Padded capacities; a column's distinct sets are at most these.
  const int64_t Kcap[kTypes] = {round_up(Kg, L), round_up(Ko, L), round_up(Kd, L), 1};
  const int64_t Kmax = std::max(std::max(Kcap[kGround], Kcap[kStatic]), Kcap[kDynamic]);
  // Thread-local buffers, reused for every column of this range.
  std::vector<Cell<T>> cells(n);
  std::vector<T> Pref[kTypes];  // (n + 1) x Kp_T: prefix-summed flow cost, cell-major
  std::vector<double> acc(Kmax);
  std::vector<T> MH[kTypes];    // nc x Kp_T running minimum per (class, hypothesis), class-major
  std::vector<I> MB[kTypes];    // its segment bottom
  std::vector<int8_t> kbest[kTypes];  // n x Kp'_T: best predecessor type per (bottom, hypothesis)
  std::vector<T> gk(Kmax), p_rule(n * kTypes);
  std::vector<T> hg(Kcap[kGround]), ho(Kcap[kStatic]), hd(Kcap[kDynamic] * 3);  // distinct, padded
  std::vector<T> inv_pg(Kcap[kGround]), inv_po(Kcap[kStatic]);
  std::vector<int32_t> table, keep(std::max(Kg, Ko));
  // The DP state of one column per (cell boundary, type) (solver.solve_columns' E, pS, gS, tauS and
  // back-pointers bpB, bpK, bpC): energy, inverse depth, reference ground, tau, segment bottom,
  // predecessor type, class.
  const int64_t S = (n + 1) * kTypes;
  std::vector<T> Ebuf(S), pSbuf(S), gSbuf(S), tSbuf(2 * S);
  std::vector<int64_t> bBbuf(S), bKbuf(S), bCbuf(S);
  for (int T_ = 0; T_ < kTypes; ++T_) {
    Pref[T_].resize((n + 1) * Kcap[T_]);
    MH[T_].resize(Kcap[T_] * ncs[T_]);
    MB[T_].resize(Kcap[T_] * ncs[T_]);
    kbest[T_].resize(n * ((T_ == kGround || T_ == kStatic) ? Kcap[T_] : 1));
  }

  // Columns are taken in small chunks from a shared counter instead of one fixed share per
  // thread: on a shared machine a descheduled thread then delays the others by one chunk, not
  // by its whole share (static splits made 2-thread runs slower than 1-thread runs under load).
  // (Chunks of kChunk columns: a few ms of work, so the wait at the end stays short.)
  for (int64_t start; (start = next.fetch_add(kChunk)) < C;)
  for (int64_t col = start; col < std::min(start + kChunk, C); ++col) {
    // ---- per-cell inputs
    for (int64_t j = 0; j < n; ++j) {
      Cell<T>& c = cells[j];
      const int64_t cj = col * n + j;
      c.up = u[col] + flow[cj * 2 + 0];
      c.vp = v[j] + flow[cj * 2 + 1];
      c.c00 = cov_inv[cj * 4 + 0];
      c.c01x2 = T(2) * cov_inv[cj * 4 + 1];
      c.c11 = cov_inv[cj * 4 + 3];
      c.logdet = logdet[cj];
      c.rows = rows[j];
      c.a0 = a[cj * 3 + 0];
      c.a1 = a[cj * 3 + 1];
      c.a2 = a[cj * 3 + 2];
      c.sg = s_g[cj];
      c.so = s_o[cj];
    }
    // ---- distinct hypotheses, padded to whole vectors with copies of the last one
    const T* pg = p_ground + col * Kg;
    const T* po = p_object + col * Ko;
    const T* gd = g_dyn + col * Kd * 3;
    int64_t K[kTypes], Kp[kTypes];
    K[kGround] = first_occurrences(pg, Kg, table, keep.data());
    Kp[kGround] = round_up(K[kGround], L);
    for (int64_t k = 0; k < Kp[kGround]; ++k) hg[k] = pg[keep[std::min(k, K[kGround] - 1)]];
    K[kStatic] = first_occurrences(po, Ko, table, keep.data());
    Kp[kStatic] = round_up(K[kStatic], L);
    for (int64_t k = 0; k < Kp[kStatic]; ++k) ho[k] = po[keep[std::min(k, K[kStatic] - 1)]];
    K[kDynamic] = Kd;  // (dynamic hypotheses are (tx, ty) pairs; copies are rare there)
    Kp[kDynamic] = Kcap[kDynamic];
    for (int64_t k = 0; k < Kp[kDynamic]; ++k)
      for (int d = 0; d < 3; ++d) hd[k * 3 + d] = gd[std::min(k, Kd - 1) * 3 + d];
    K[kSky] = Kp[kSky] = 1;

    const T cK0 = cK[col * 3 + 0], cK1 = cK[col * 3 + 1], cK2 = cK[col * 3 + 2];
    flow_prefix<T, kGround>(P, cells, Kp[kGround], hg.data(), cK0, cK1, cK2, acc.data(), Pref[kGround].data());
    flow_prefix<T, kStatic>(P, cells, Kp[kStatic], ho.data(), cK0, cK1, cK2, acc.data(), Pref[kStatic].data());
    flow_prefix<T, kDynamic>(P, cells, Kp[kDynamic], hd.data(), cK0, cK1, cK2, acc.data(), Pref[kDynamic].data());
    flow_prefix<T, kSky>(P, cells, 1, nullptr, cK0, cK1, cK2, acc.data(), Pref[kSky].data());

    // ---- the DP (solver.solve_columns, hard minima)
    T *Ec = Ebuf.data(), *pSc = pSbuf.data(), *gSc = gSbuf.data(), *tSc = tSbuf.data();
    int64_t *bB = bBbuf.data(), *bK = bKbuf.data(), *bC = bCbuf.data();
    const T pref = p_ref[col];
    for (int64_t s = 0; s < S; ++s) {
      Ec[s] = inf;
      pSc[s] = pref;
      gSc[s] = pref;
      bB[s] = bK[s] = bC[s] = 0;
      tSc[2 * s] = tSc[2 * s + 1] = T(0);
    }
    Ec[kGround] = T(0);  // virtual ground stixel at the camera height
    for (int T_ = 0; T_ < kTypes; ++T_) {
      std::fill(MH[T_].begin(), MH[T_].begin() + Kp[T_] * ncs[T_], inf);
      std::fill(MB[T_].begin(), MB[T_].begin() + Kp[T_] * ncs[T_], 0);
    }
    for (int64_t k = 0; k < Kp[kGround]; ++k) inv_pg[k] = T(1) / hg[k];
    for (int64_t k = 0; k < Kp[kStatic]; ++k) inv_po[k] = T(1) / ho[k];
    const bool deg = degenerate[col];
    const T* Lc = Lp + col * ncl * (n + 1);
    const T* qc = q + col * n;

    for (int64_t i = 0; i < n; ++i) {
      const T* Ep = Ec + i * kTypes;
      const T* pp = pSc + i * kTypes;
      const T* gp = gSc + i * kTypes;
      const T qi = qc[i];
      T inv_gp[kTypes], inv_pp[kTypes], st_rule[kTypes];
      int act[kTypes], nact = 0;  // reachable predecessor types, ascending
      for (int j = 0; j < kTypes; ++j) {
        inv_gp[j] = T(1) / gp[j];
        const T ppc = pp[j] < P.p_min ? P.p_min : pp[j];
        inv_pp[j] = is_object(j) ? T(1) / ppc : T(1);
        T pr = is_object(j) ? pp[j] : qi * gp[j];
        pr = pr < P.p_min ? P.p_min : pr;
        pr = pr > P.p_max ? P.p_max : pr;
        p_rule[i * kTypes + j] = pr;
        const T inv_pr = T(1) / pr;
        st_rule[j] = structural(P, inv_pr, qi * inv_pr, inv_pp[j], inv_gp[j], j);
        if (Ep[j] < inf) act[nact++] = j;
      }
      for (int T_ = 0; T_ < kTypes; ++T_) {
        const int64_t Kt = Kp[T_], nc = ncs[T_];
        const bool per_k = (T_ == kGround || T_ == kStatic);
        const T* P0 = Pref[T_].data() + i * Kt;
        const T* P1 = P0 + Kt;
        int8_t* kbi = kbest[T_].data() + i * (per_k ? Kt : 1);
        // Best predecessor type per hypothesis (ground, static) or for the whole type, and
        // gk = G - P0 for the segments that start at cell i.
        if (T_ == kGround || (T_ == kStatic && !deg)) {
          const T* ip = T_ == kGround ? inv_pg.data() : inv_po.data();
          for (int64_t k = 0; k < Kt; k += L) {
            const V ipk = load<V>(ip + k);
            const V qip = qi * ipk;  // (static) q * inv_p, shared by every predecessor
            V G = vinf;
            VI kb = splat<VI>(0);
            for (int aa = 0; aa < nact; ++aa) {
              const int j = act[aa];
              V st;
              if (T_ == kGround) {
                const V dh = inv_gp[j] - ipk;
                st = P.a_flat + P.b_flat * dh * dh;  // flat ground (paper Ψ_flat)
              } else {
                st = structural(P, ipk, qip, inv_pp[j], inv_gp[j], j);
              }
              const V cand = Ep[j] + st;
              const VI lt = cand < G;
              G = lt ? cand : G;
              kb = lt ? splat<VI>(j) : kb;
            }
            store(kbi + k, __builtin_convertvector(kb, VB));
            store(gk.data() + k, G - load<V>(P0 + k));
          }
        } else {
          T G0;
          int32_t kb0;
          if (T_ == kSky) {  // no structural prior: Ep + 0 == Ep exactly, as in the eager path
            best_predecessor(Ep, G0, kb0, [&](int) { return T(0); });
          } else {  // dynamic, or static under degenerate motion: the scene model's depth
            best_predecessor(Ep, G0, kb0, [&](int j) { return st_rule[j]; });
          }
          if (per_k) {
            std::fill(kbi, kbi + Kt, static_cast<int8_t>(kb0));
          } else {
            kbi[0] = static_cast<int8_t>(kb0);
          }
          for (int64_t k = 0; k < Kt; ++k) gk[k] = G0 - P0[k];
        }
        for (int64_t k = K[T_]; k < Kt; ++k) gk[k] = inf;  // padding: never opens a segment
        const int64_t* ct = cls_table + T_ * 3;
        T L0[kMaxClasses], L1[kMaxClasses];
        for (int64_t c = 0; c < nc; ++c) {
          const int64_t cl = has_sem ? ct[c] : 0;
          L0[c] = Lc[cl * (n + 1) + i];
          L1[c] = Lc[cl * (n + 1) + i + 1];
        }
        T* mh = MH[T_].data();
        I* mb = MB[T_].data();
        const I ii = static_cast<I>(i);
        T val;
        int64_t h_star, c_star;
        if (T_ == kSky) {  // one hypothesis: scalar, classes in ascending order
          val = inf;
          h_star = c_star = 0;
          for (int64_t c = 0; c < nc; ++c) {
            const T cH = gk[0] - L0[c];
            if (cH < mh[c]) { mh[c] = cH; mb[c] = ii; }
            const T tot = mh[c] + (P1[0] + L1[c]);
            if (tot < val) { val = tot; c_star = c; }
          }
        } else if (nc == 3) {
          close_segments<T, 3>(Kt, gk.data(), P1, mh, mb, L0, L1, ii, val, h_star, c_star);
        } else if (nc == 2) {
          close_segments<T, 2>(Kt, gk.data(), P1, mh, mb, L0, L1, ii, val, h_star, c_star);
        } else {
          close_segments<T, 1>(Kt, gk.data(), P1, mh, mb, L0, L1, ii, val, h_star, c_star);
        }
        const int64_t s = (i + 1) * kTypes + T_;
        Ec[s] = val + P.beta_mc;
        const int64_t b_star = mb[c_star * Kt + h_star];
        const int64_t k_star = kbest[T_][b_star * (per_k ? Kt : 1) + (per_k ? h_star : 0)];
        const T g_pred = gSc[b_star * kTypes + k_star];
        T p_new, g_new = g_pred;
        if (T_ == kGround) {
          p_new = hg[h_star];
          g_new = p_new;
        } else if (T_ == kStatic) {
          p_new = deg ? p_rule[b_star * kTypes + k_star] : ho[h_star];
        } else if (T_ == kDynamic) {
          p_new = p_rule[b_star * kTypes + k_star];
          tSc[2 * s] = tau[(col * Kd + h_star) * 2];
          tSc[2 * s + 1] = tau[(col * Kd + h_star) * 2 + 1];
        } else {
          p_new = T(0);
        }
        pSc[s] = p_new;
        gSc[s] = g_new;
        bB[s] = b_star;
        bK[s] = k_star;
        bC[s] = has_sem ? ct[c_star] : ct[0];
      }
    }

    // ---- back-tracking (solver._backtrack): from the cheapest type at the top (the first on
    // ties, like torch.argmin) down the back-pointers to the virtual start; the column's stixels
    // bottom-up. energy = min over the types (torch.amin), cost = E(top) - E(predecessor).
    const T* et = Ec + n * kTypes;
    int64_t top = 0;
    for (int j = 1; j < kTypes; ++j)
      if (et[j] < et[top]) top = j;
    energy[col] = et[top];
    const size_t first = out.size();
    for (int64_t i = n, ty = top; i > 0;) {
      const int64_t s = i * kTypes + ty, bb = bB[s], kk = bK[s];
      out.push_back({col, bb, i - 1, ty, bC[s], pSc[s], gSc[s], tSc[2 * s], tSc[2 * s + 1], Ec[s] - Ec[bb * kTypes + kk]});
      i = bb;
      ty = kk;
    }
    std::reverse(out.begin() + first, out.end());
  }
}

std::vector<at::Tensor> column_dp(const at::Tensor& a, const at::Tensor& cK, const at::Tensor& s_g,
                                  const at::Tensor& s_o, const at::Tensor& u, const at::Tensor& v,
                                  const at::Tensor& rows, const at::Tensor& flow, const at::Tensor& cov_inv,
                                  const at::Tensor& logdet, const at::Tensor& p_ground, const at::Tensor& p_object,
                                  const at::Tensor& g_dyn, const at::Tensor& tau, const at::Tensor& Lp,
                                  const at::Tensor& q, const at::Tensor& p_ref, const at::Tensor& degenerate,
                                  const at::Tensor& params, const at::Tensor& cls_table, const at::Tensor& ncs,
                                  bool has_sem) {
  const int64_t C = a.size(0), n = a.size(1);
  const int64_t Kg = p_ground.size(1), Ko = p_object.size(1), Kd = g_dyn.size(1), ncl = Lp.size(1);
  TORCH_CHECK(Kd > 0 && Kg > 0 && Ko > 0, "column_dp: empty hypothesis set");
  TORCH_CHECK(Lp.size(2) == n + 1, "column_dp: semantic prefix must have n + 1 entries");
  const auto opt = a.options();
  auto energy = at::empty({C}, opt);
  std::vector<at::Tensor> out;
  auto deg = degenerate.to(at::kBool).contiguous();
  auto cls = cls_table.to(at::kLong).contiguous();
  auto nc = ncs.to(at::kLong).contiguous();
  AT_DISPATCH_FLOATING_TYPES(a.scalar_type(), "column_dp", [&] {
    using T = scalar_t;
    auto cont = [&](const at::Tensor& x, const char* name) { return contiguous_as(x, a, "column_dp", name); };
    auto a_ = cont(a, "a"), cK_ = cont(cK, "cK"), sg_ = cont(s_g, "s_g"), so_ = cont(s_o, "s_o");
    auto u_ = cont(u, "u"), v_ = cont(v, "v"), rows_ = cont(rows, "rows"), fl_ = cont(flow, "flow");
    auto ci_ = cont(cov_inv, "cov_inv"), ld_ = cont(logdet, "logdet"), pg_ = cont(p_ground, "p_ground");
    auto po_ = cont(p_object, "p_object"), gd_ = cont(g_dyn, "g_dyn"), ta_ = cont(tau, "tau");
    auto L_ = cont(Lp, "Lp"), q_ = cont(q, "q"), pr_ = cont(p_ref, "p_ref"), prm_ = cont(params, "params");
    const T* pv = prm_.data_ptr<T>();
    Params<T> P{pv[0], pv[1], pv[2], pv[3], pv[4], pv[5], pv[6], pv[7], pv[8], pv[9], pv[10], pv[11],
                pv[12], pv[13], pv[14], pv[15]};
    std::atomic<int64_t> next{0};
    const int64_t workers = std::min<int64_t>(at::get_num_threads(), (C + kChunk - 1) / kChunk);
    std::vector<std::vector<Stixel<T>>> lists(workers);  // one per worker, its columns ascending
    at::parallel_for(0, workers, 1, [&](int64_t w0, int64_t) {
      solve_columns<T>(next, C, n, Kg, Ko, Kd, ncl, P, a_.data_ptr<T>(), cK_.data_ptr<T>(), sg_.data_ptr<T>(),
                     so_.data_ptr<T>(), u_.data_ptr<T>(), v_.data_ptr<T>(), rows_.data_ptr<T>(), fl_.data_ptr<T>(),
                     ci_.data_ptr<T>(), ld_.data_ptr<T>(), pg_.data_ptr<T>(), po_.data_ptr<T>(), gd_.data_ptr<T>(),
                     ta_.data_ptr<T>(), L_.data_ptr<T>(), q_.data_ptr<T>(), pr_.data_ptr<T>(), deg.data_ptr<bool>(),
                     cls.data_ptr<int64_t>(), nc.data_ptr<int64_t>(), has_sem, energy.data_ptr<T>(), lists[w0]);
    });
    // The stixel table in column order (each column's stixels are contiguous in one list).
    std::vector<int64_t> offset(C + 1, 0);
    for (const auto& lst : lists)
      for (const auto& st : lst) ++offset[st.col + 1];
    for (int64_t c = 0; c < C; ++c) offset[c + 1] += offset[c];
    const int64_t N = offset[C];
    auto lopt = opt.dtype(at::kLong);
    auto col = at::empty({N}, lopt), b = at::empty({N}, lopt), t = at::empty({N}, lopt);
    auto type = at::empty({N}, lopt), cl = at::empty({N}, lopt);
    auto p = at::empty({N}, opt), g = at::empty({N}, opt), tau2 = at::empty({N, 2}, opt), cost = at::empty({N}, opt);
    int64_t *o_col = col.data_ptr<int64_t>(), *o_b = b.data_ptr<int64_t>(), *o_t = t.data_ptr<int64_t>();
    int64_t *o_type = type.data_ptr<int64_t>(), *o_cls = cl.data_ptr<int64_t>();
    T *o_p = p.data_ptr<T>(), *o_g = g.data_ptr<T>(), *o_tau = tau2.data_ptr<T>(), *o_cost = cost.data_ptr<T>();
    for (const auto& lst : lists) {
      for (const auto& st : lst) {
        const int64_t r = offset[st.col]++;
        o_col[r] = st.col;
        o_b[r] = st.b;
        o_t[r] = st.t;
        o_type[r] = st.type;
        o_cls[r] = st.cls;
        o_p[r] = st.p;
        o_g[r] = st.p_ground;
        o_tau[2 * r] = st.tau0;
        o_tau[2 * r + 1] = st.tau1;
        o_cost[r] = st.cost;
      }
    }
    out = {col, b, t, type, cl, p, g, tau2, cost};
  });
  out.push_back(energy);
  return out;
}

// Sums (B, ch, n, C) of x (B, ch, H, W) over cells of r rows counted from the image bottom and
// columns of w pixels (columns._block_sum, in its order: a row's pixels left to right, then the
// cell's rows bottom-up, a missing top row adding 0), so the two give the same bits.
//
// Two layouts are read in place: planes of contiguous rows (flow, scores), and CH channels
// interleaved per pixel (the covariance (H, W, 2, 2) seen as (B, 4, H, W)); CH = 0 and W_ = 0
// take the channel count and the column width at run time, fixed ones let the compiler unroll
// the sum of a cell's row (the default column width, 5, and the 4 covariance entries).
//
// The same pass checks the values (solver._check_values), so that the inputs, tens of MB that
// do not stay in cache, are read once: every sum finite (a NaN or inf pixel makes its cell's sum
// NaN or inf), and per pixel either x >= 0 (scores) or a positive definite 2 x 2 matrix
// (c00 > 0 and det > 0, det in the order of solver._check_values). A failed check only means
// "look closer": the solver then runs its own checks, which name the problem.
enum CellCheck : int64_t { kNoCheck = 0, kFinite = 1, kNonNegative = 2, kPositiveDefinite = 3 };

// out[e][l] = x[4 l + e] for the L pixels l of 4 entries e at x: two rounds of two-vector shuffles
// (pick4: entries E0 of the first half of the pixels in x, y, then entries E1; halves: the
// lower or upper halves of x and y).
template <int E0, int E1, typename V, size_t... Is>
inline V pick4(const V& x, const V& y, std::index_sequence<Is...>) {
  constexpr size_t H = sizeof...(Is) / 2;
  return __builtin_shufflevector(x, y, (Is < H ? 4 * Is + E0 : 4 * (Is - H) + E1)...);
}
template <int Off, typename V, size_t... Is>
inline V halves(const V& x, const V& y, std::index_sequence<Is...>) {
  constexpr size_t H = sizeof...(Is) / 2;
  return __builtin_shufflevector(x, y, (Is < H ? Is + Off : sizeof...(Is) + Is - H + Off)...);
}
template <typename T>
inline void deinterleave4(const T* x, typename Simd<T>::V* out) {
  using V = typename Simd<T>::V;
  constexpr int64_t N = kLanes<T>;
  const auto seq = std::make_index_sequence<N>{};
  const V v0 = load<V>(x), v1 = load<V>(x + N), v2 = load<V>(x + 2 * N), v3 = load<V>(x + 3 * N);
  const V a01 = pick4<0, 1>(v0, v1, seq), a23 = pick4<2, 3>(v0, v1, seq);  // pixels 0 .. N/2 - 1
  const V b01 = pick4<0, 1>(v2, v3, seq), b23 = pick4<2, 3>(v2, v3, seq);  // pixels N/2 .. N - 1
  out[0] = halves<0>(a01, b01, seq);
  out[1] = halves<N / 2>(a01, b01, seq);
  out[2] = halves<0>(a23, b23, seq);
  out[3] = halves<N / 2>(a23, b23, seq);
}

// The row sums of one image row: row[k * C + c] for channel k and column c. Returns false where
// a pixel fails the per-pixel check.
template <typename T, int W_, int CH_>
inline bool cell_row_sums(const T* xv, int64_t W, int64_t w, int64_t C, int64_t ch, T* row, int64_t check) {
  const int64_t nch = CH_ ? CH_ : ch, cw = W_ ? W_ : w;
  const int64_t full = W / cw;
  if (CH_ == 1) {  // planar: the plain loop, which the compiler vectorises over the cells
    for (int64_t c = 0; c < full; ++c) {
      const T* px = xv + c * cw;
      T a = px[0];
      for (int64_t uu = 1; uu < cw; ++uu) a = a + px[uu];
      row[c] = a;
    }
  }
  for (int64_t c = 0; c < (CH_ == 1 ? 0 : full); ++c) {
    const T* px = xv + c * cw * nch;
    T acc[CH_ ? CH_ : 1];
    if (CH_) {
      for (int64_t k = 0; k < nch; ++k) acc[k] = px[k];
      for (int64_t uu = 1; uu < cw; ++uu)
        for (int64_t k = 0; k < nch; ++k) acc[k] = acc[k] + px[uu * nch + k];
      for (int64_t k = 0; k < nch; ++k) row[k * C + c] = acc[k];
    } else {
      for (int64_t k = 0; k < nch; ++k) {
        T a = px[k];
        for (int64_t uu = 1; uu < cw; ++uu) a = a + px[uu * nch + k];
        row[k * C + c] = a;
      }
    }
  }
  if (full < C) {  // a partial last column sums the pixels it has
    const T* px = xv + full * cw * nch;
    const int64_t left = W - full * cw;
    for (int64_t k = 0; k < nch; ++k) {
      T a = px[k];
      for (int64_t uu = 1; uu < left; ++uu) a = a + px[uu * nch + k];
      row[k * C + full] = a;
    }
  }
  using V = typename Simd<T>::V;
  using VI = typename Simd<T>::VI;
  constexpr int64_t L = kLanes<T>;
  VI badv{};  // whole vectors (the row is in L1 now), then the rest one by one
  bool bad = false;
  if (check == kNonNegative) {
    int64_t e = 0;
    for (; e + L <= W * nch; e += L) badv |= load<V>(xv + e) < T(0);
    for (; e < W * nch; ++e) bad |= xv[e] < T(0);
  } else if (check == kPositiveDefinite && nch == kCovEntries) {
    int64_t uu = 0;
    for (; uu + L <= W; uu += L) {  // L pixels: their 4 entries deinterleaved
      V m[kCovEntries];
      deinterleave4(xv + uu * kCovEntries, m);
      const V det = m[0] * m[3] - m[1] * m[2];
      badv |= ~(m[0] > T(0)) | ~(det > T(0));
    }
    for (; uu < W; ++uu) {
      const T* m = xv + uu * kCovEntries;  // c00, c01, c10, c11
      const T det = m[0] * m[3] - m[1] * m[2];
      bad |= !(m[0] > T(0)) | !(det > T(0));
    }
  }
  for (int64_t l = 0; l < L; ++l) bad |= badv[l] != 0;
  return !bad;
}

// x: image b at x + b * img_stride; pixel (v, u) channel k at v * row_stride + u * CH + k with
// CH channels interleaved per pixel (CH_ > 1, or 0 for a count taken at run time), or at
// k * chan_stride + v * row_stride + u in planes of rows (CH_ = 1). Cell (i, c) of channel k of
// image b goes to out[b * o_b + k * o_k + i * o_i + c * o_c], divided by count[i * C + c] if
// count is given. Returns whether the values pass `check`.
template <typename T, int W_, int CH_>
bool cell_sums_impl(const T* x, T* out, int64_t B, int64_t ch, int64_t img_stride, int64_t chan_stride,
                    int64_t row_stride, int64_t H, int64_t W, int64_t r, int64_t w, int64_t check, const T* count,
                    int64_t o_b, int64_t o_k, int64_t o_i, int64_t o_c) {
  const int64_t n = (H + r - 1) / r, C = (W + w - 1) / w;
  const bool planar = CH_ == 1;
  // Work items (image, cell row) from a shared counter, like the columns of the DP: a thread
  // that the OS deschedules on a shared machine then holds up one row of cells, not half the image.
  std::atomic<int64_t> next{0};
  std::atomic<bool> ok{true};
  const int64_t items = B * n;
  const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), items / 16));
  at::parallel_for(0, workers, 1, [&](int64_t, int64_t) {
    std::vector<T> rows(r * ch * C), cell(ch * C);
    bool good = true;
    for (int64_t item; (item = next.fetch_add(1)) < items;) {
      // Memory is read in ascending order (the top cell row first, its image rows top-down):
      // the hardware prefetchers follow that, not the bottom-up order of the sums (3x slower).
      const int64_t b = item / n, i = n - 1 - item % n;
      const T* xb = x + b * img_stride;
      for (int64_t k = 0; k < (planar ? ch : 1); ++k) {
        for (int64_t jj = r - 1; jj >= 0; --jj) {
          const int64_t v = H - 1 - (i * r + jj);  // image row
          T* row = rows.data() + jj * ch * C + k * C;
          if (v < 0) {  // above the image (a partial top cell): adds 0
            std::fill(row, row + (planar ? 1 : ch) * C, T(0));
          } else if (planar) {
            good &= cell_row_sums<T, W_, 1>(xb + k * chan_stride + v * row_stride, W, w, C, 1, row, check);
          } else {
            good &= cell_row_sums<T, W_, CH_>(xb + v * row_stride, W, w, C, ch, row, check);
          }
        }
      }
      std::copy(rows.begin(), rows.begin() + ch * C, cell.begin());
      for (int64_t jj = 1; jj < r; ++jj) {  // the cell's rows added bottom-up
        const T* row = rows.data() + jj * ch * C;
        for (int64_t e = 0; e < ch * C; ++e) cell[e] = cell[e] + row[e];
      }
      if (check != kNoCheck) {
        bool fin = true;
        for (int64_t e = 0; e < ch * C; ++e) fin &= std::isfinite(cell[e]);
        good &= fin;
      }
      T* op = out + b * o_b + i * o_i;
      for (int64_t c = 0; c < C; ++c)
        for (int64_t k = 0; k < ch; ++k)
          op[k * o_k + c * o_c] = count ? cell[k * C + c] / count[i * C + c] : cell[k * C + c];
    }
    if (!good) ok = false;
  });
  return ok;
}

// The default column width (conf/solver/default.yaml): its cell rows are summed unrolled.
constexpr int kUnrolledWidth = 5;

// Without `count`: the sums (B, ch, n, C). With count (n, C), the cell's pixel count: the means
// sum / count (the division of solver._prepare) in memory (B, C, n, ch), the layout of the
// solver's per-column arrays.
std::tuple<at::Tensor, at::Tensor> cell_sums(const at::Tensor& x, int64_t r, int64_t w, int64_t check,
                                             const c10::optional<at::Tensor>& count) {
  TORCH_CHECK(x.dim() == 4, "cell_sums: x must be (B, ch, H, W), got ", x.dim(), " dims");
  TORCH_CHECK(r >= 1 && w >= 1, "cell_sums: r and w must be >= 1");
  TORCH_CHECK(check >= kNoCheck && check <= kPositiveDefinite, "cell_sums: unknown check ", check);
  const int64_t B = x.size(0), ch = x.size(1), H = x.size(2), W = x.size(3);
  const int64_t n = (H + r - 1) / r, C = (W + w - 1) / w;
  TORCH_CHECK(check != kPositiveDefinite || ch == kCovEntries, "cell_sums: a 2 x 2 matrix has 4 entries, got ", ch);
  const bool means = count.has_value() && count->defined();
  at::Tensor cnt;
  if (means) {
    TORCH_CHECK(count->dim() == 2 && count->size(0) == n && count->size(1) == C, "cell_sums: count must be (n, C)");
    TORCH_CHECK(count->scalar_type() == x.scalar_type(), "cell_sums: count has dtype ", count->scalar_type());
    cnt = count->contiguous();
  }
  auto out = means ? at::empty({B, C, n, ch}, x.options()) : at::empty({B, ch, n, C}, x.options());
  // Channels interleaved per pixel, images one after another (a permuted (B, H, W, ch) tensor):
  // read in place. Anything else is made contiguous (planes of rows).
  // (The stride of a dimension of size 1 is arbitrary.)
  auto stride_is = [&](int d, int64_t s) { return x.size(d) == 1 || x.stride(d) == s; };
  const bool interleaved = ch > 1 && x.stride(1) == 1 && stride_is(3, ch) && stride_is(2, W * ch) &&
                           stride_is(0, H * W * ch);
  TORCH_CHECK(check != kPositiveDefinite || interleaved, "cell_sums: the matrix check needs (B, H, W, 4) memory");
  auto xc = interleaved ? x : x.contiguous();
  const int64_t img_stride = H * W * ch, chan_stride = interleaved ? 1 : H * W, row_stride = interleaved ? W * ch : W;
  // Output strides of (image b, channel k, cell row i, column c).
  const int64_t o_b = ch * n * C, o_k = means ? 1 : n * C, o_i = means ? ch : C, o_c = means ? n * ch : 1;
  bool ok = true;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cell_sums", [&] {
    using T = scalar_t;
    const T* xp = xc.data_ptr<T>();
    T* op = out.data_ptr<T>();
    const T* cp = means ? cnt.data_ptr<T>() : nullptr;
    const bool w5 = w == kUnrolledWidth;
    auto impl = !interleaved ? (w5 ? cell_sums_impl<T, kUnrolledWidth, 1> : cell_sums_impl<T, 0, 1>)
                : ch == kCovEntries ? (w5 ? cell_sums_impl<T, kUnrolledWidth, kCovEntries> : cell_sums_impl<T, 0, kCovEntries>)
                                    : cell_sums_impl<T, 0, 0>;
    ok = impl(xp, op, B, ch, img_stride, chan_stride, row_stride, H, W, r, w, check, cp, o_b, o_k, o_i, o_c);
  });
  return {out, at::scalar_tensor(ok, x.options().dtype(at::kBool))};
}

// Per-cell geometry of every column (columns._geometry, in the order of its torch ops): the
// ray K^-1 x of each cell centre (geometry.pixel_rays), a = K R K^-1 x, s = n^T K^-1 x for the
// ground and object normals, and the bottom-ray ratio q (columns._bottom_ray_ratio). The 3 x 3
// products add like torch's small-matrix bmm (from 0, in index order) and the 3-term dot
// products like its sum over the last dimension (from 0, then its 3 idle partial sums, which
// only turn a zero sum of -0 into +0).
template <typename T>
inline T sum3(const T* x) {
  T acc = T(0);
  for (int k = 0; k < 3; ++k) acc = acc + x[k];
  return acc + T(0) + T(0) + T(0);
}

template <typename T>
inline void pixel_ray(const T* K, T u, T v, T* ray) {
  const T fx = K[0], s = K[1], cx = K[2], fy = K[4], cy = K[5];
  const T y = (v - cy) / fy;
  ray[0] = (u - cx - s * y) / fx;
  ray[1] = y;
  ray[2] = T(1);
}

template <typename T>
void geometry_impl(int64_t C, int64_t n, const T* K, const T* KR, const T* n_g, const T* n_obj, const T* u,
                   const T* v, const T* v_edge, T* ray, T* a, T* s_g, T* s_o, T* q) {
  at::parallel_for(0, C, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      const T *Kc = K + c * 9, *M = KR + c * 9, *ng = n_g + c * 3, *no = n_obj + c * 3;
      for (int64_t j = 0; j < n; ++j) {
        const int64_t cj = c * n + j;
        T* r = ray + cj * 3;
        pixel_ray(Kc, u[c], v[j], r);
        for (int i = 0; i < 3; ++i) {
          T acc = T(0);
          for (int k = 0; k < 3; ++k) acc = acc + M[i * 3 + k] * r[k];
          a[cj * 3 + i] = acc;
        }
        T rb[3], p_g[3], p_o[3];  // (ray * n) of the torch code, then its sum
        for (int k = 0; k < 3; ++k) { p_g[k] = r[k] * ng[k]; p_o[k] = r[k] * no[k]; }
        s_g[cj] = sum3(p_g);
        s_o[cj] = sum3(p_o);
        pixel_ray(Kc, u[c], v_edge[j], rb);  // the ray through the cell's lower edge
        for (int k = 0; k < 3; ++k) { p_g[k] = rb[k] * ng[k]; p_o[k] = rb[k] * no[k]; }
        q[cj] = sum3(p_g) / sum3(p_o);
      }
    }
  });
}

std::vector<at::Tensor> geometry(const at::Tensor& K, const at::Tensor& KR, const at::Tensor& n_g,
                                 const at::Tensor& n_obj, const at::Tensor& u, const at::Tensor& v,
                                 const at::Tensor& v_edge) {
  const int64_t C = u.size(0), n = v.size(0);
  const auto opt = u.options();
  auto ray = at::empty({C, n, 3}, opt), a = at::empty({C, n, 3}, opt);
  auto s_g = at::empty({C, n}, opt), s_o = at::empty({C, n}, opt), q = at::empty({C, n}, opt);
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "geometry", [&] {
    using T = scalar_t;
    auto cont = [&](const at::Tensor& x, const char* name) { return contiguous_as(x, u, "geometry", name); };
    auto K_ = cont(K, "K"), KR_ = cont(KR, "KR"), ng_ = cont(n_g, "n_g"), no_ = cont(n_obj, "n_obj");
    auto u_ = cont(u, "u"), v_ = cont(v, "v"), ve_ = cont(v_edge, "v_edge");
    geometry_impl<T>(C, n, K_.data_ptr<T>(), KR_.data_ptr<T>(), ng_.data_ptr<T>(), no_.data_ptr<T>(),
                     u_.data_ptr<T>(), v_.data_ptr<T>(), ve_.data_ptr<T>(), ray.data_ptr<T>(), a.data_ptr<T>(),
                     s_g.data_ptr<T>(), s_o.data_ptr<T>(), q.data_ptr<T>());
  });
  return {ray, a, s_g, s_o, q};
}

// Prefix-summed semantic cost (C, 10, n + 1) of every column (columns.semantic_prefix, in the
// order of its torch ops): min(nll, alpha_L) * rows * delta_L per cell and class, plus extra[j] where
// the cell's `unseen` bits (if given: 1 = no sky there, 2 = no ground there) meet the class's `rule`
// bits, summed in double like torch.cumsum on the CPU.
template <typename T>
void semantic_prefix_impl(int64_t C, int64_t n, int64_t ncl, const T* nll, const T* rows, T alpha_L, T delta_L,
                          const uint8_t* unseen, const T* extra, const uint8_t* rule, T* Lp) {
  at::parallel_for(0, C, 1, [&](int64_t c0, int64_t c1) {
    std::vector<double> acc(ncl);
    for (int64_t c = c0; c < c1; ++c) {
      T* L = Lp + c * ncl * (n + 1);
      std::fill(acc.begin(), acc.end(), 0.0);
      for (int64_t k = 0; k < ncl; ++k) L[k * (n + 1)] = T(0);
      for (int64_t j = 0; j < n; ++j) {
        const T* x = nll + (c * n + j) * ncl;
        for (int64_t k = 0; k < ncl; ++k) {
          const T m = alpha_L < x[k] ? alpha_L : x[k];  // torch.minimum (no NaN here)
          T e = m * rows[j] * delta_L;
          if (unseen != nullptr && (unseen[c * n + j] & rule[k])) e = e + extra[j];
          acc[k] += static_cast<double>(e);
          L[k * (n + 1) + j + 1] = static_cast<T>(acc[k]);
        }
      }
    }
  });
}

at::Tensor semantic_prefix(const at::Tensor& nll, const at::Tensor& rows, const at::Tensor& alpha_L,
                           const at::Tensor& delta_L, const c10::optional<at::Tensor>& unseen,
                           const c10::optional<at::Tensor>& extra, const at::Tensor& rule) {
  const int64_t C = nll.size(0), n = nll.size(1), ncl = nll.size(2);
  TORCH_CHECK(rule.numel() == ncl, "semantic_prefix: rule has ", rule.numel(), " entries for ", ncl, " classes");
  auto Lp = at::empty({C, ncl, n + 1}, nll.options());
  const bool has = unseen.has_value() && unseen->defined();
  auto un = has ? unseen->to(at::kByte).contiguous() : at::Tensor();
  auto ru = rule.to(at::kByte).contiguous();
  AT_DISPATCH_FLOATING_TYPES(nll.scalar_type(), "semantic_prefix", [&] {
    using T = scalar_t;
    auto nll_ = nll.contiguous(), rows_ = rows.to(nll.scalar_type()).contiguous();
    auto ex = has ? extra->to(nll.scalar_type()).contiguous() : at::Tensor();
    semantic_prefix_impl<T>(C, n, ncl, nll_.data_ptr<T>(), rows_.data_ptr<T>(), alpha_L.item<T>(),
                            delta_L.item<T>(), has ? un.data_ptr<uint8_t>() : nullptr,
                            has ? ex.data_ptr<T>() : nullptr, ru.data_ptr<uint8_t>(), Lp.data_ptr<T>());
  });
  return Lp;
}

// Hypothesis sets of every column for hypothesis_stride = 1 (columns._hypotheses with
// columns._fits, in the order of their torch ops): each cell's own static fits for the ground and
// object normals (geometry.static_dof_system + solve_static_dof), its dynamic fit
// (dynamic_dof_system + solve_dynamic_dof), the standing depths, the replacements of missing
// ones, and g = K B tau of the dynamic ones (columns._flow_geometry). The systems' 2-term sums are written x0 + x1: torch's reduction adds the same two
// numbers (and zeros, which only change the sign of a zero sum: such a fit is p = +-0, outside
// [p_min, p_max], so it is dropped either way).
template <typename T>
void hypotheses_impl(int64_t C, int64_t n, const T* a, const T* cK, const T* s_g, const T* s_o, const T* q,
                     const T* u, const T* v, const T* flow, const T* M, const T* p_ref, const bool* degenerate,
                     T p_min, T p_max, T eps, bool standing, T* pg, T* po, T* tau, T* g) {
  const T nan = std::numeric_limits<T>::quiet_NaN();
  const int64_t Kg = n + 1, Ko = standing ? 2 * n : n;
  auto valid = [&](T p) { return (std::isfinite(p) && p >= p_min && p <= p_max) ? p : nan; };
  at::parallel_for(0, C, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      const T* Mc = M + c * 6;  // K B, 3 x 2
      const T cK0 = cK[c * 3], cK1 = cK[c * 3 + 1], cK2 = cK[c * 3 + 2], pr = p_ref[c];
      for (int64_t j = 0; j < n; ++j) {
        const int64_t cj = c * n + j;
        const T up = u[c] + flow[cj * 2], vp = v[j] + flow[cj * 2 + 1];
        const T* ac = a + cj * 3;
        const T b0 = ac[0] - up * ac[2], b1 = ac[1] - vp * ac[2];
        const T cu = up * cK2 - cK0, cv = vp * cK2 - cK1;
        auto fit = [&](T s) {
          const T A0 = s * cu, A1 = s * cv;
          const T den = A0 * A0 + A1 * A1;
          const T p = (A0 * b0 + A1 * b1) / den;
          return valid(den > eps ? p : nan);
        };
        T p_g = fit(s_g[cj]);
        if (degenerate[c]) p_g = nan;  // without translation the ground is the reference ground
        pg[c * Kg + j] = std::isnan(p_g) ? pr : p_g;
        const T p_o = fit(s_o[cj]);
        po[c * Ko + j] = std::isnan(p_o) ? p_min : p_o;
        if (standing) {
          const T p_s = valid(q[cj] * pr);
          po[c * Ko + n + j] = std::isnan(p_s) ? p_min : p_s;
        }
        const T s = s_o[cj];
        const T A00 = s * (up * Mc[4] - Mc[0]), A01 = s * (up * Mc[5] - Mc[1]);
        const T A10 = s * (vp * Mc[4] - Mc[2]), A11 = s * (vp * Mc[5] - Mc[3]);
        const T det = A00 * A11 - A01 * A10;
        const bool ok = std::abs(det) > eps;
        const T tx = ok ? (A11 * b0 - A01 * b1) / det : nan;
        const T ty = ok ? (A00 * b1 - A10 * b0) / det : nan;
        const T t0 = std::isfinite(tx) ? tx : T(0), t1 = std::isfinite(ty) ? ty : T(0);
        tau[cj * 2] = t0;
        tau[cj * 2 + 1] = t1;
        for (int r = 0; r < 3; ++r) {  // g = K B tau, added like torch's small-matrix bmm
          T acc = T(0);
          acc = acc + Mc[r * 2] * t0;
          acc = acc + Mc[r * 2 + 1] * t1;
          g[cj * 3 + r] = acc;
        }
      }
      pg[c * Kg + n] = pr;  // the reference ground is always a hypothesis
    }
  });
}

std::vector<at::Tensor> hypotheses(const at::Tensor& a, const at::Tensor& cK, const at::Tensor& s_g,
                                   const at::Tensor& s_o, const at::Tensor& q, const at::Tensor& u,
                                   const at::Tensor& v, const at::Tensor& flow, const at::Tensor& M,
                                   const at::Tensor& p_ref, const at::Tensor& degenerate, double p_min, double p_max,
                                   double eps, bool standing) {
  const int64_t C = a.size(0), n = a.size(1);
  const auto opt = a.options();
  auto pg = at::empty({C, n + 1}, opt);
  auto po = at::empty({C, standing ? 2 * n : n}, opt);
  auto tau = at::empty({C, n, 2}, opt);
  auto g = at::empty({C, n, 3}, opt);
  auto deg = degenerate.to(at::kBool).contiguous();
  AT_DISPATCH_FLOATING_TYPES(a.scalar_type(), "hypotheses", [&] {
    using T = scalar_t;
    auto cont = [&](const at::Tensor& x, const char* name) { return contiguous_as(x, a, "hypotheses", name); };
    auto a_ = cont(a, "a"), cK_ = cont(cK, "cK"), sg_ = cont(s_g, "s_g"), so_ = cont(s_o, "s_o"), q_ = cont(q, "q");
    auto u_ = cont(u, "u"), v_ = cont(v, "v"), fl_ = cont(flow, "flow"), M_ = cont(M, "M"), pr_ = cont(p_ref, "p_ref");
    hypotheses_impl<T>(C, n, a_.data_ptr<T>(), cK_.data_ptr<T>(), sg_.data_ptr<T>(), so_.data_ptr<T>(),
                       q_.data_ptr<T>(), u_.data_ptr<T>(), v_.data_ptr<T>(), fl_.data_ptr<T>(), M_.data_ptr<T>(),
                       pr_.data_ptr<T>(), deg.data_ptr<bool>(), static_cast<T>(p_min), static_cast<T>(p_max),
                       static_cast<T>(eps), standing, pg.data_ptr<T>(), po.data_ptr<T>(), tau.data_ptr<T>(),
                       g.data_ptr<T>());
  });
  return {pg, po, tau, g};
}

}  // namespace

TORCH_LIBRARY(monostixels, m) {
  m.def("cell_sums(Tensor x, int r, int w, int check, Tensor? count) -> (Tensor, Tensor)");
  m.def("geometry(Tensor K, Tensor KR, Tensor n_g, Tensor n_obj, Tensor u, Tensor v, Tensor v_edge) -> Tensor[]");
  m.def(
      "semantic_prefix(Tensor nll, Tensor rows, Tensor alpha_L, Tensor delta_L, Tensor? unseen, Tensor? extra, "
      "Tensor rule) -> Tensor");
  m.def(
      "hypotheses(Tensor a, Tensor cK, Tensor s_g, Tensor s_o, Tensor q, Tensor u, Tensor v, Tensor flow, "
      "Tensor M, Tensor p_ref, Tensor degenerate, float p_min, float p_max, float eps, bool standing) -> Tensor[]");
  m.def(
      "column_dp(Tensor a, Tensor cK, Tensor s_g, Tensor s_o, Tensor u, Tensor v, Tensor rows, Tensor flow, "
      "Tensor cov_inv, Tensor logdet, Tensor p_ground, Tensor p_object, Tensor g_dyn, Tensor tau, Tensor Lp, "
      "Tensor q, Tensor p_ref, Tensor degenerate, Tensor params, Tensor cls_table, Tensor ncs, bool has_sem) "
      "-> Tensor[]");
}

TORCH_LIBRARY_IMPL(monostixels, CPU, m) {
  m.impl("column_dp", &column_dp);
  m.impl("cell_sums", &cell_sums);
  m.impl("hypotheses", &hypotheses);
  m.impl("geometry", &geometry);
  m.impl("semantic_prefix", &semantic_prefix);
}
