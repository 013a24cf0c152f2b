// Fused hard column DP of the mono-stixel solver (tau == 0): the C++ twin of the eager stage
// loop in monostixels/solver.py (`_flow_prefix` + the loop of `solve_columns`).
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
// Layout: all inputs are contiguous, of one floating dtype (float32 or float64); C columns,
// n cells (cell 0 at the image bottom), Kg / Ko / Kd hypotheses of ground / object / dynamic.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

namespace {

constexpr int kTypes = 4;  // ground, static object, dynamic object, sky
constexpr int64_t kChunk = 2;  // columns a thread takes at a time
constexpr int kGround = 0, kStatic = 1, kDynamic = 2, kSky = 3;
inline bool is_object(int j) { return j == kStatic || j == kDynamic; }

// Eight lanes of T (GCC/Clang vector extension) for the minimum over all hypotheses.
template <typename T>
struct LanesOf;
template <>
struct LanesOf<float> { typedef float type __attribute__((vector_size(32))); };
template <>
struct LanesOf<double> { typedef double type __attribute__((vector_size(64))); };
template <typename T>
using Lanes = typename LanesOf<T>::type;
// Integers of T's width (segment bottoms, flat indices): their vectors share T's comparison masks.
template <typename T>
struct IdxOf;
template <>
struct IdxOf<float> { using type = int32_t; typedef int32_t vec __attribute__((vector_size(32))); };
template <>
struct IdxOf<double> { using type = int64_t; typedef int64_t vec __attribute__((vector_size(64))); };
template <typename T>
using IdxLanes = typename IdxOf<T>::vec;

template <typename V, typename S>
inline V splat(S s) {
  V v;
  for (int l = 0; l < 8; ++l) v[l] = s;
  return v;
}

// Prior parameters, in the order of `_PARAM_ORDER` in monostixels/_dp_cpp.py.
template <typename T>
struct Params {
  T beta_mc, a_gb, b_gb, a_ga, b_ga, a_ord, b_ord, a_flat, b_flat, alpha_F, delta_F, alpha_dyn;
  T p_min, p_max, grav_tol, z_min;
};

// Ψ_str of an object with depth 1/inv_p above predecessor type j (energy.gravity and
// energy.ordering_from_depths, combined as in solver._structural_object).
template <typename T>
inline T structural(const Params<T>& P, T inv_p, T q, T inv_pp, T inv_gp, int j) {
  const T dh = inv_gp - q * inv_p;
  const T grav = (dh < -P.grav_tol) ? P.a_gb + P.b_gb * (-dh) : P.a_ga + P.b_ga * dh;
  if (!is_object(j)) return grav;
  const T d = inv_pp - inv_p;
  const T ord = (d > T(0)) ? P.a_ord + P.b_ord * d : T(0);
  return ord < grav ? ord : grav;  // torch.minimum (no NaN here)
}

// Per-cell inputs of the flow cost of one column (solver._row_costs).
template <typename T>
struct Cell {
  T up, vp, c00, c01x2, c11, logdet, rows, a0, a1, a2, sg, so;
};

// Robust flow cost of one cell for predicted point (h0, h1, h2), weighted by rows (solver._row_costs).
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
// cell-major (solver._flow_prefix). Double accumulators like torch.cumsum on the CPU. The inner
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
    if (impossible) {  // ground above / sky below the horizon (solver.beyond_horizon)
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

// G[k] = min_j Ep[j] + st(j, k) and kb[k] = the first j attaining it (torch.min semantics): types
// in ascending order with a strict "<", starting from +inf / 0. Unreachable predecessors
// (Ep = inf) never win a strict minimum and are skipped.
template <typename T, typename St>
inline void best_predecessor(const T* Ep, int64_t K, T* G, int32_t* kb, St&& st) {
  const T inf = std::numeric_limits<T>::infinity();
  for (int64_t k = 0; k < K; ++k) { G[k] = inf; kb[k] = 0; }
  for (int j = 0; j < kTypes; ++j) {
    if (!(Ep[j] < inf)) continue;
    const T e = Ep[j];
    for (int64_t k = 0; k < K; ++k) {
      const T cand = e + st(j, k);
      const bool lt = cand < G[k];
      G[k] = lt ? cand : G[k];
      kb[k] = lt ? j : kb[k];
    }
  }
}

template <typename T>
void solve_columns(std::atomic<int64_t>& next, int64_t C, int64_t n, int64_t Kg, int64_t Ko, int64_t Kd, int64_t ncl,
                 const Params<T>& P, const T* a, const T* cK, const T* s_g, const T* s_o, const T* u,
                 const T* v, const T* rows, const T* flow, const T* cov_inv, const T* logdet,
                 const T* p_ground, const T* p_object, const T* g_dyn, const T* tau, const T* Lp,
                 const T* q, const T* p_ref, const bool* degenerate, const int64_t* cls_table,
                 const int64_t* ncs, bool has_sem, T* E, T* pS, T* gS, T* tauS, int64_t* bpB,
                 int64_t* bpK, int64_t* bpC) {
  const T inf = std::numeric_limits<T>::infinity();
  const int64_t Ks[kTypes] = {Kg, Ko, Kd, 1};
  const int64_t Kmax = std::max(std::max(Kg, Ko), Kd);
  // Thread-local buffers, reused for every column of this range.
  std::vector<Cell<T>> cells(n);
  std::vector<T> Pref[kTypes];  // (n + 1) x K_T: prefix-summed flow cost, cell-major
  std::vector<double> acc(Kmax);
  std::vector<T> MH[kTypes];    // nc x K_T running minimum per (class, hypothesis), class-major
  std::vector<typename IdxOf<T>::type> MB[kTypes];  // its segment bottom
  std::vector<int8_t> kbest[kTypes];  // n x K'_T: best predecessor type per (bottom, hypothesis)
  std::vector<T> G(Kmax), gk(Kmax);
  std::vector<int32_t> kb(Kmax);
  std::vector<T> p_rule(n * kTypes), inv_pg(Kg), inv_po(Ko);
  for (int T_ = 0; T_ < kTypes; ++T_) {
    Pref[T_].resize((n + 1) * Ks[T_]);
    MH[T_].resize(Ks[T_] * ncs[T_]);
    MB[T_].resize(Ks[T_] * ncs[T_]);
    kbest[T_].resize(n * ((T_ == kGround || T_ == kStatic) ? Ks[T_] : 1));
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
    const T cK0 = cK[col * 3 + 0], cK1 = cK[col * 3 + 1], cK2 = cK[col * 3 + 2];
    const T* pg = p_ground + col * Kg;
    const T* po = p_object + col * Ko;
    const T* gd = g_dyn + col * Kd * 3;
    flow_prefix<T, kGround>(P, cells, Kg, pg, cK0, cK1, cK2, acc.data(), Pref[kGround].data());
    flow_prefix<T, kStatic>(P, cells, Ko, po, cK0, cK1, cK2, acc.data(), Pref[kStatic].data());
    flow_prefix<T, kDynamic>(P, cells, Kd, gd, cK0, cK1, cK2, acc.data(), Pref[kDynamic].data());
    flow_prefix<T, kSky>(P, cells, 1, nullptr, cK0, cK1, cK2, acc.data(), Pref[kSky].data());

    // ---- the DP (solver.solve_columns, hard minima)
    T* Ec = E + col * (n + 1) * kTypes;
    T* pSc = pS + col * (n + 1) * kTypes;
    T* gSc = gS + col * (n + 1) * kTypes;
    T* tSc = tauS + col * (n + 1) * kTypes * 2;
    int64_t* bB = bpB + col * (n + 1) * kTypes;
    int64_t* bK = bpK + col * (n + 1) * kTypes;
    int64_t* bC = bpC + col * (n + 1) * kTypes;
    const T pref = p_ref[col];
    for (int64_t s = 0; s < (n + 1) * kTypes; ++s) {
      Ec[s] = inf;
      pSc[s] = pref;
      gSc[s] = pref;
      bB[s] = bK[s] = bC[s] = 0;
      tSc[2 * s] = tSc[2 * s + 1] = T(0);
    }
    Ec[kGround] = T(0);  // virtual ground stixel at the camera height
    for (int T_ = 0; T_ < kTypes; ++T_) {
      std::fill(MH[T_].begin(), MH[T_].end(), inf);
      std::fill(MB[T_].begin(), MB[T_].end(), 0);
    }
    for (int64_t k = 0; k < Kg; ++k) inv_pg[k] = T(1) / pg[k];
    for (int64_t k = 0; k < Ko; ++k) inv_po[k] = T(1) / po[k];
    const bool deg = degenerate[col];
    const T* Lc = Lp + col * ncl * (n + 1);
    const T* qc = q + col * n;

    for (int64_t i = 0; i < n; ++i) {
      const T* Ep = Ec + i * kTypes;
      const T* pp = pSc + i * kTypes;
      const T* gp = gSc + i * kTypes;
      const T qi = qc[i];
      T inv_gp[kTypes], inv_pp[kTypes], st_rule[kTypes];
      for (int j = 0; j < kTypes; ++j) {
        inv_gp[j] = T(1) / gp[j];
        const T ppc = pp[j] < P.p_min ? P.p_min : pp[j];
        inv_pp[j] = is_object(j) ? T(1) / ppc : T(1);
        T pr = is_object(j) ? pp[j] : qi * gp[j];
        pr = pr < P.p_min ? P.p_min : pr;
        pr = pr > P.p_max ? P.p_max : pr;
        p_rule[i * kTypes + j] = pr;
        st_rule[j] = structural(P, T(1) / pr, qi, inv_pp[j], inv_gp[j], j);
      }
      for (int T_ = 0; T_ < kTypes; ++T_) {
        const int64_t K = Ks[T_], nc = ncs[T_];
        const bool per_k = (T_ == kGround || T_ == kStatic);
        // Best predecessor type per hypothesis (per_k) or for the whole type.
        if (T_ == kGround) {
          best_predecessor(Ep, K, G.data(), kb.data(), [&](int j, int64_t k) {
            const T dh = inv_gp[j] - inv_pg[k];
            return P.a_flat + P.b_flat * dh * dh;  // flat ground (paper Ψ_flat)
          });
        } else if (T_ == kStatic && !deg) {
          best_predecessor(Ep, K, G.data(), kb.data(), [&](int j, int64_t k) {
            return structural(P, inv_po[k], qi, inv_pp[j], inv_gp[j], j);
          });
        } else if (T_ == kStatic) {  // degenerate motion: the scene model's depth for every hypothesis
          best_predecessor(Ep, 1, G.data(), kb.data(), [&](int j, int64_t) { return st_rule[j]; });
          for (int64_t k = 1; k < K; ++k) { G[k] = G[0]; kb[k] = kb[0]; }
        } else if (T_ == kDynamic) {
          best_predecessor(Ep, 1, G.data(), kb.data(), [&](int j, int64_t) { return st_rule[j]; });
        } else {
          // Sky has no structural prior: Ep + 0 == Ep exactly, as in the eager path.
          best_predecessor(Ep, 1, G.data(), kb.data(), [&](int, int64_t) { return T(0); });
        }
        int8_t* kbi = kbest[T_].data() + i * (per_k ? K : 1);
        for (int64_t k = 0; k < (per_k ? K : 1); ++k) kbi[k] = static_cast<int8_t>(kb[k]);
        const T* P0 = Pref[T_].data() + i * K;
        const T* P1 = P0 + K;
        if (per_k) {
          for (int64_t k = 0; k < K; ++k) gk[k] = G[k] - P0[k];
        } else {
          for (int64_t k = 0; k < K; ++k) gk[k] = G[0] - P0[k];
        }
        const int64_t* ct = cls_table + T_ * 3;
        // Running minimum over segment bottoms per (class, hypothesis), and the segments that end
        // at cell i closed with the prefix sums at i + 1; the minimum over all of them.
        // Running minimum over segment bottoms per (class, hypothesis), the segments that end at
        // cell i closed with the prefix sums at i + 1, and the first (hypothesis-major, like the
        // eager flatten) index of their minimum: 8 hypotheses at a time (vector extension; the
        // compiler does not vectorise an argmin by itself). Ties go to the lower flat index.
        using V = Lanes<T>;
        using VI = IdxLanes<T>;
        using I = typename IdxOf<T>::type;
        V best = splat<V>(inf);
        VI bidx = splat<VI>(std::numeric_limits<I>::max());
        T best_s = inf;
        I bidx_s = std::numeric_limits<I>::max();
        const I ii = static_cast<I>(i);
        const VI iiv = splat<VI>(ii);
        VI koff;
        for (int l = 0; l < 8; ++l) koff[l] = static_cast<I>(l);
        for (int64_t c = 0; c < nc; ++c) {
          const int64_t cl = has_sem ? ct[c] : 0;
          const T L0 = Lc[cl * (n + 1) + i], L1 = Lc[cl * (n + 1) + i + 1];
          T* mh = MH[T_].data() + c * K;
          I* mb = MB[T_].data() + c * K;
          int64_t k = 0;
          for (; k + 8 <= K; k += 8) {
            V g, m, p1;
            VI bb;
            std::memcpy(&g, gk.data() + k, sizeof(V));
            std::memcpy(&m, mh + k, sizeof(V));
            std::memcpy(&p1, P1 + k, sizeof(V));
            std::memcpy(&bb, mb + k, sizeof(VI));
            const V cH = g - L0;
            const auto lt = cH < m;
            m = lt ? cH : m;
            bb = lt ? iiv : bb;
            std::memcpy(mh + k, &m, sizeof(V));
            std::memcpy(mb + k, &bb, sizeof(VI));
            const V tot_v = m + (p1 + L1);
            const VI flat = (koff + static_cast<I>(k)) * static_cast<I>(nc) + static_cast<I>(c);
            const auto better = (tot_v < best) | ((tot_v == best) & (flat < bidx));
            best = better ? tot_v : best;
            bidx = better ? flat : bidx;
          }
          for (; k < K; ++k) {
            const T cH = gk[k] - L0;
            if (cH < mh[k]) { mh[k] = cH; mb[k] = ii; }
            const T tot_s = mh[k] + (P1[k] + L1);
            const I flat = static_cast<I>(k * nc + c);
            if (tot_s < best_s || (tot_s == best_s && flat < bidx_s)) { best_s = tot_s; bidx_s = flat; }
          }
        }
        T val = best_s;
        I arg = bidx_s;
        for (int l = 0; l < 8; ++l)
          if (best[l] < val || (best[l] == val && bidx[l] < arg)) { val = best[l]; arg = bidx[l]; }
        const int64_t h_star = arg / nc, c_star = arg % nc;
        const int64_t s = (i + 1) * kTypes + T_;
        Ec[s] = val + P.beta_mc;
        const int64_t b_star = MB[T_][c_star * K + h_star];
        const int64_t k_star = kbest[T_][b_star * (per_k ? K : 1) + (per_k ? h_star : 0)];
        const T g_pred = gSc[b_star * kTypes + k_star];
        T p_new, g_new = g_pred;
        if (T_ == kGround) {
          p_new = pg[h_star];
          g_new = p_new;
        } else if (T_ == kStatic) {
          p_new = deg ? p_rule[b_star * kTypes + k_star] : po[h_star];
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
  auto E = at::empty({C, n + 1, kTypes}, opt);
  auto pS = at::empty({C, n + 1, kTypes}, opt);
  auto gS = at::empty({C, n + 1, kTypes}, opt);
  auto tauS = at::empty({C, n + 1, kTypes, 2}, opt);
  auto lopt = opt.dtype(at::kLong);
  auto bpB = at::empty({C, n + 1, kTypes}, lopt);
  auto bpK = at::empty({C, n + 1, kTypes}, lopt);
  auto bpC = at::empty({C, n + 1, kTypes}, lopt);
  auto deg = degenerate.to(at::kBool).contiguous();
  auto cls = cls_table.to(at::kLong).contiguous();
  auto nc = ncs.to(at::kLong).contiguous();
  AT_DISPATCH_FLOATING_TYPES(a.scalar_type(), "column_dp", [&] {
    using T = scalar_t;
    auto cont = [&](const at::Tensor& x, const char* name) {
      TORCH_CHECK(x.scalar_type() == a.scalar_type(), "column_dp: ", name, " has dtype ", x.scalar_type(),
                  ", expected ", a.scalar_type());
      return x.contiguous();
    };
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
    at::parallel_for(0, workers, 1, [&](int64_t, int64_t) {
      solve_columns<T>(next, C, n, Kg, Ko, Kd, ncl, P, a_.data_ptr<T>(), cK_.data_ptr<T>(), sg_.data_ptr<T>(),
                     so_.data_ptr<T>(), u_.data_ptr<T>(), v_.data_ptr<T>(), rows_.data_ptr<T>(), fl_.data_ptr<T>(),
                     ci_.data_ptr<T>(), ld_.data_ptr<T>(), pg_.data_ptr<T>(), po_.data_ptr<T>(), gd_.data_ptr<T>(),
                     ta_.data_ptr<T>(), L_.data_ptr<T>(), q_.data_ptr<T>(), pr_.data_ptr<T>(), deg.data_ptr<bool>(),
                     cls.data_ptr<int64_t>(), nc.data_ptr<int64_t>(), has_sem, E.data_ptr<T>(), pS.data_ptr<T>(),
                     gS.data_ptr<T>(), tauS.data_ptr<T>(), bpB.data_ptr<int64_t>(), bpK.data_ptr<int64_t>(),
                     bpC.data_ptr<int64_t>());
    });
  });
  return {E, pS, gS, tauS, bpB, bpK, bpC};
}

// Sums (B, ch, n, C) of x (B, ch, H, W) over cells of r rows counted from the image bottom and
// columns of w pixels (solver._block_sum, in its order: a row's pixels left to right, then the
// cell's rows bottom-up, a missing top row adding 0), so the two give the same bits.
template <typename T>
void cell_sums_impl(const T* x, T* out, int64_t planes, int64_t H, int64_t W, int64_t r, int64_t w) {
  const int64_t n = (H + r - 1) / r, C = (W + w - 1) / w;
  // Work items (plane, cell row) from a shared counter, like the columns of the DP: a thread
  // that the OS deschedules on a shared machine then holds up one row of cells, not half the image.
  std::atomic<int64_t> next{0};
  const int64_t items = planes * n;
  const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), items / 16));
  at::parallel_for(0, workers, 1, [&](int64_t, int64_t) {
    std::vector<T> row(C);
    for (int64_t item; (item = next.fetch_add(1)) < items;) {
      const int64_t p = item / n, i = item % n;
      const T* xp = x + p * H * W;
      T* oi = out + p * n * C + i * C;
      for (int64_t jj = 0; jj < r; ++jj) {
        const int64_t v = H - 1 - (i * r + jj);  // image row, bottom-up
        if (v >= 0) {
          const T* xv = xp + v * W;
          for (int64_t c = 0; c < C; ++c) {
            const int64_t u0 = c * w, u1 = std::min(u0 + w, W);
            T acc = xv[u0];
            for (int64_t u = u0 + 1; u < u1; ++u) acc = acc + xv[u];
            row[c] = acc;
          }
        } else {
          std::fill(row.begin(), row.end(), T(0));
        }
        if (jj == 0) {
          std::copy(row.begin(), row.end(), oi);
        } else {
          for (int64_t c = 0; c < C; ++c) oi[c] = oi[c] + row[c];
        }
      }
    }
  });
}

at::Tensor cell_sums(const at::Tensor& x, int64_t r, int64_t w) {
  TORCH_CHECK(x.dim() == 4, "cell_sums: x must be (B, ch, H, W), got ", x.dim(), " dims");
  TORCH_CHECK(r >= 1 && w >= 1, "cell_sums: r and w must be >= 1");
  const int64_t B = x.size(0), ch = x.size(1), H = x.size(2), W = x.size(3);
  const int64_t n = (H + r - 1) / r, C = (W + w - 1) / w;
  auto xc = x.contiguous();
  auto out = at::empty({B, ch, n, C}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cell_sums", [&] {
    cell_sums_impl<scalar_t>(xc.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), B * ch, H, W, r, w);
  });
  return out;
}

}  // namespace

TORCH_LIBRARY(monostixels, m) {
  m.def("cell_sums(Tensor x, int r, int w) -> Tensor");
  m.def(
      "column_dp(Tensor a, Tensor cK, Tensor s_g, Tensor s_o, Tensor u, Tensor v, Tensor rows, Tensor flow, "
      "Tensor cov_inv, Tensor logdet, Tensor p_ground, Tensor p_object, Tensor g_dyn, Tensor tau, Tensor Lp, "
      "Tensor q, Tensor p_ref, Tensor degenerate, Tensor params, Tensor cls_table, Tensor ncs, bool has_sem) "
      "-> Tensor[]");
}

TORCH_LIBRARY_IMPL(monostixels, CPU, m) {
  m.impl("column_dp", &column_dp);
  m.impl("cell_sums", &cell_sums);
}
