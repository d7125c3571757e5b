// The multigrid-preconditioned CG of crfdepth/linalg/multigrid.py and crfdepth/linalg/cg.py in three fused
// passes per iteration (docs/design.md section 4b). The eager path (GridMultigrid's V-cycle through
// adjoint._scaled_multigrid in cg.py's _cg_loop, a convergence check after every iteration) is the reference the
// tests compare against (tests/linalg/test_native_multigrid.py).
//
// The V-cycle of a level is two passes: down (damped Jacobi from zero, the residual and its 2 x 2 block sums into
// the next level's right-hand side) and up (the prolonged correction added, the residual and the second damped
// Jacobi step). The smoothed iterates are never stored: each task keeps a ring of three rows (the rows next to
// its own are computed again). The finest level runs in the Jacobi-scaled form of the CG (M = D^-1/2 A D^-1/2 =
// I - W', r_s = D^-1/2 r): the preconditioner D^1/2 B D^1/2 of _scaled_multigrid is there damped Jacobi by omega
// on M (the same arithmetic up to rounding), so neither D nor omega / D of that level is read. A CG iteration:
//   A: p = z + beta p, and p . M p (alpha)                        [z, p, the scaled weights]
//   B: y += alpha p, r -= alpha M p (M p again), sum D r^2, and the V-cycle's first down pass   [r, p, y, sq]
//   C: the coarser levels, the finest up pass: z and r . z (beta)  [r, sq, z]
// The levels' setup (coarsening, the dense inverse of the coarsest) stays in Python (GridMultigrid.__init__).
//
// Sums: in T within a row, in double over rows, added in row order: the results do not depend on the thread
// count. The row kernels are separate (noinline) functions with __restrict__ arguments: inlined into the tasks'
// lambdas, GCC 12 left some `omp simd reduction` loops scalar.

#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace crfdepth_multigrid {

namespace {
namespace mg {

constexpr int64_t kCells = 8192;  // pixels per task at least

int64_t grain_rows(int64_t cells_per_row) {
  return std::max<int64_t>(1, kCells / std::max<int64_t>(1, cells_per_row));
}

template <typename F>
double sum_rows(int64_t rows, int64_t grain, F&& row_sum) {
  std::vector<double> partial(rows, 0.0);
  at::parallel_for(0, rows, grain, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) partial[r] = row_sum(r);
  });
  double total = 0.0;
  for (double v : partial) total += v;
  return total;
}

// One level of one grid: the operator diag(dg) - W (wh (h, w-1), wv (h-1, w)), omega / dg in jac, and the
// level's right-hand side r and correction z (levels >= 1). The finest level: the scaled weights, no dg / jac.
template <typename T>
struct Level {
  int64_t h = 1, w = 1, fh = 1, fw = 1, h2 = 1, w2 = 1;
  const T* dg = nullptr;
  const T* jac = nullptr;
  const T* wh = nullptr;
  const T* wv = nullptr;
  T* r = nullptr;
  T* z = nullptr;
};

template <typename T>
struct Cycle {
  std::vector<Level<T>> levels;  // [0]: the finest, scaled
  const double* cinv = nullptr;  // (m, m) inverse of the coarsest level's matrix
  double* cwork = nullptr;       // m doubles
  const T* sq = nullptr;         // D^1/2 of the finest level
  const T* zero = nullptr;       // zeros, as long as the widest row
  T omega = T(0.8);
};

// t = r - dg x + W x on one row (x: centre row xc, the rows above xu and below xd, zero rows where absent).
// kUnit: dg = 1 (the scaled finest level). Terms in the order of _Level.residual.
template <typename T, bool kUnit>
__attribute__((noinline)) void residual_row(const T* __restrict__ r, const T* __restrict__ dg,
                                            const T* __restrict__ xc, const T* __restrict__ xu,
                                            const T* __restrict__ xd, const T* __restrict__ whr,
                                            const T* __restrict__ wu, const T* __restrict__ wd, T* __restrict__ t,
                                            int64_t w) {
  auto edge = [&](int64_t j) {
    T v = r[j] - (kUnit ? xc[j] : dg[j] * xc[j]);
    if (j + 1 < w) v += whr[j] * xc[j + 1];
    if (j > 0) v += whr[j - 1] * xc[j - 1];
    v += wd[j] * xd[j];
    v += wu[j] * xu[j];
    return v;
  };
  t[0] = edge(0);
  if (w > 1) t[w - 1] = edge(w - 1);
  if (kUnit) {
#pragma omp simd
    for (int64_t j = 1; j < w - 1; ++j)
      t[j] = r[j] - xc[j] + whr[j] * xc[j + 1] + whr[j - 1] * xc[j - 1] + wd[j] * xd[j] + wu[j] * xu[j];
  } else {
#pragma omp simd
    for (int64_t j = 1; j < w - 1; ++j)
      t[j] = r[j] - dg[j] * xc[j] + whr[j] * xc[j + 1] + whr[j - 1] * xc[j - 1] + wd[j] * xd[j] + wu[j] * xu[j];
  }
}

// x = coef r (coef: jac, or omega where jac is null)
template <typename T>
__attribute__((noinline)) void smooth_row(const T* __restrict__ r, const T* __restrict__ jac, T omega,
                                          T* __restrict__ x, int64_t w) {
  if (jac == nullptr) {
#pragma omp simd
    for (int64_t j = 0; j < w; ++j) x[j] = omega * r[j];
  } else {
#pragma omp simd
    for (int64_t j = 0; j < w; ++j) x[j] = jac[j] * r[j];
  }
}

// x = coef r + s (P e) on one row: e the coarse row, s = sq (the scaled finest level) or 1 (sq null)
template <typename T>
__attribute__((noinline)) void prolong_row(const T* __restrict__ r, const T* __restrict__ jac, T omega,
                                           const T* __restrict__ sq, const T* __restrict__ e, T* __restrict__ x,
                                           int64_t w, int64_t fw) {
  smooth_row<T>(r, jac, omega, x, w);
  if (fw == 1) {
    if (sq == nullptr) {
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) x[j] += e[j];
    } else {
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) x[j] += sq[j] * e[j];
    }
    return;
  }
  const int64_t pairs = w / 2;
  if (sq == nullptr) {
#pragma omp simd
    for (int64_t k = 0; k < pairs; ++k) {
      x[2 * k] += e[k];
      x[2 * k + 1] += e[k];
    }
    if (w % 2) x[w - 1] += e[pairs];
  } else {
#pragma omp simd
    for (int64_t k = 0; k < pairs; ++k) {
      x[2 * k] += sq[2 * k] * e[k];
      x[2 * k + 1] += sq[2 * k + 1] * e[k];
    }
    if (w % 2) x[w - 1] += sq[w - 1] * e[pairs];
  }
}

// out[J] = a[fw J] + a[fw J + 1] (the columns of a block; a lone last column alone)
template <typename T>
__attribute__((noinline)) void pair_columns(const T* __restrict__ a, T* __restrict__ out, int64_t w, int64_t fw) {
  if (fw == 1) {
    std::copy(a, a + w, out);
    return;
  }
  const int64_t pairs = w / 2;
#pragma omp simd
  for (int64_t k = 0; k < pairs; ++k) out[k] = a[2 * k] + a[2 * k + 1];
  if (w % 2) out[pairs] = a[w - 1];
}

template <typename T>
__attribute__((noinline)) void add_rows(T* __restrict__ acc, const T* __restrict__ t, int64_t w) {
#pragma omp simd
  for (int64_t j = 0; j < w; ++j) acc[j] += t[j];
}

template <typename T>
__attribute__((noinline)) void scale_row(T* __restrict__ t, const T* __restrict__ s, int64_t w) {
#pragma omp simd
  for (int64_t j = 0; j < w; ++j) t[j] *= s[j];
}

// z = x + coef t; returns sum r z when kDot
template <typename T, bool kDot>
__attribute__((noinline)) T correct_row(const T* __restrict__ x, const T* __restrict__ t, const T* __restrict__ jac,
                                        T omega, const T* __restrict__ r, T* __restrict__ z, int64_t w) {
  T acc = 0;
  if (jac == nullptr) {
#pragma omp simd reduction(+ : acc)
    for (int64_t j = 0; j < w; ++j) {
      const T v = x[j] + omega * t[j];
      z[j] = v;
      if (kDot) acc += r[j] * v;
    }
  } else {
#pragma omp simd reduction(+ : acc)
    for (int64_t j = 0; j < w; ++j) {
      const T v = x[j] + jac[j] * t[j];
      z[j] = v;
      if (kDot) acc += r[j] * v;
    }
  }
  return acc;
}

// The rows of the block sums P^T t: row i of t (of h rows, w wide) into the coarse row i / fh of rc, through acc.
template <typename T>
inline void restrict_row(int64_t i, T* t, T* acc, T* rc, int64_t h, int64_t w, int64_t fh, int64_t fw, int64_t w2) {
  if (fh == 1) {
    pair_columns<T>(t, rc + i * w2, w, fw);
  } else if (i % 2 == 0 && i + 1 < h) {
    std::copy(t, t + w, acc);  // the block's top row; its bottom row comes next
  } else if (i % 2 == 0) {
    pair_columns<T>(t, rc + (i / 2) * w2, w, fw);  // a last block one row high
  } else {
    add_rows<T>(acc, t, w);
    pair_columns<T>(acc, rc + (i / 2) * w2, w, fw);
  }
}

// t = row i of r - A x on level L (unit: the finest level's scaled form, without its diagonal), with x's rows
// i - 1, i, i + 1 in a task's ring of three smoothed rows and zero rows beyond the grid.
template <typename T>
void ring_residual(const Level<T>& L, const T* r, T* const* ring, const T* zero, int64_t i, T* t) {
  const int64_t h = L.h, w = L.w;
  const bool up = i > 0, down = i + 1 < h;
  const T* xu = up ? ring[(i - 1) % 3] : zero;
  const T* wu = up ? L.wv + (i - 1) * w : zero;
  const T* xd = down ? ring[(i + 1) % 3] : zero;
  const T* wd = down ? L.wv + i * w : zero;
  if (L.dg == nullptr) {
    residual_row<T, true>(r + i * w, nullptr, ring[i % 3], xu, xd, L.wh + i * (w - 1), wu, wd, t, w);
  } else {
    residual_row<T, false>(r + i * w, L.dg + i * w, ring[i % 3], xu, xd, L.wh + i * (w - 1), wu, wd, t, w);
  }
}

// The down pass of level L on its right-hand side r: x = coef r, t = r - A x, rc = P^T (s t) (s = sq on the
// scaled finest level, where A is M; else 1), written to the next level's right-hand side rc.
template <typename T>
void down_pass(const Level<T> L, const T* r, const T* sq, T omega, const T* zero, T* rc) {
  const int64_t h = L.h, w = L.w, fh = L.fh, fw = L.fw, w2 = L.w2;
  const bool unit = L.dg == nullptr;
  at::parallel_for(0, L.h2, grain_rows(fh * w), [=](int64_t c0, int64_t c1) {
    std::vector<T> buf(5 * w);
    T* ring[3] = {buf.data(), buf.data() + w, buf.data() + 2 * w};
    T* t = buf.data() + 3 * w;
    T* acc = buf.data() + 4 * w;
    auto smooth = [&](int64_t i) { smooth_row<T>(r + i * w, L.jac ? L.jac + i * w : nullptr, omega, ring[i % 3], w); };
    const int64_t i0 = c0 * fh, i1 = std::min(h, c1 * fh);
    if (i0 > 0) smooth(i0 - 1);
    smooth(i0);
    for (int64_t i = i0; i < i1; ++i) {
      if (i + 1 < h) smooth(i + 1);
      ring_residual<T>(L, r, ring, zero, i, t);
      if (unit) scale_row<T>(t, sq + i * w, w);
      restrict_row<T>(i, t, acc, rc, h, w, fh, fw, w2);
    }
  });
}

// The up pass of level L: x = coef r + s P e, t = r - A x, z = x + coef t; returns sum r z when kDot.
template <typename T, bool kDot>
double up_pass(const Level<T> L, const T* r, const T* sq, T omega, const T* zero, const T* e, T* z) {
  const int64_t h = L.h, w = L.w, fh = L.fh, fw = L.fw, w2 = L.w2;
  const bool unit = L.dg == nullptr;
  std::vector<double> partial(h, 0.0);
  double* part = partial.data();
  at::parallel_for(0, h, grain_rows(w), [=](int64_t i0, int64_t i1) {
    std::vector<T> buf(4 * w);
    T* ring[3] = {buf.data(), buf.data() + w, buf.data() + 2 * w};
    T* t = buf.data() + 3 * w;
    auto prolong = [&](int64_t i) {
      prolong_row<T>(r + i * w, L.jac ? L.jac + i * w : nullptr, omega, unit ? sq + i * w : nullptr,
                     e + (i / fh) * w2, ring[i % 3], w, fw);
    };
    if (i0 > 0) prolong(i0 - 1);
    prolong(i0);
    for (int64_t i = i0; i < i1; ++i) {
      if (i + 1 < h) prolong(i + 1);
      ring_residual<T>(L, r, ring, zero, i, t);
      part[i] = static_cast<double>(
          correct_row<T, kDot>(ring[i % 3], t, L.jac ? L.jac + i * w : nullptr, omega, r + i * w, z + i * w, w));
    }
  });
  double total = 0.0;
  for (double v : partial) total += v;
  return total;
}

__attribute__((noinline)) double dot_row(const double* __restrict__ a, const double* __restrict__ b, int64_t m) {
  double acc = 0.0;
#pragma omp simd reduction(+ : acc)
  for (int64_t k = 0; k < m; ++k) acc += a[k] * b[k];
  return acc;
}

// z = C^-1 r in double, rounded to T (C^-1: (m, m)); s (may be null): r and z scaled by it (r s in T first)
template <typename T>
void coarse_solve(const double* cinv, double* work, const T* r, const T* s, T* z, int64_t m) {
  for (int64_t a = 0; a < m; ++a) work[a] = static_cast<double>(s ? s[a] * r[a] : r[a]);
  at::parallel_for(0, m, std::max<int64_t>(1, kCells / std::max<int64_t>(1, m)), [=](int64_t a0, int64_t a1) {
    for (int64_t a = a0; a < a1; ++a) {
      const T za = static_cast<T>(dot_row(cinv + a * m, work, m));
      z[a] = s ? s[a] * za : za;
    }
  });
}

// The V-cycle below the finest level's down pass (whose block sums are in levels[1].r): zs = D^1/2 B D^1/2 rs;
// returns rs . zs. A grid that is the coarsest level: the dense solve of D^1/2 rs.
template <typename T>
double finish_cycle(const Cycle<T>& cy, const T* rs, T* zs) {
  const int64_t depth = static_cast<int64_t>(cy.levels.size());
  const Level<T>& fine = cy.levels[0];
  if (depth == 1) {
    const int64_t n = fine.h * fine.w;
    coarse_solve<T>(cy.cinv, cy.cwork, rs, cy.sq, zs, n);
    double acc = 0.0;
    for (int64_t k = 0; k < n; ++k) acc += static_cast<double>(rs[k] * zs[k]);
    return acc;
  }
  for (int64_t k = 1; k + 1 < depth; ++k) {
    const Level<T>& L = cy.levels[k];
    down_pass<T>(L, L.r, nullptr, cy.omega, cy.zero, cy.levels[k + 1].r);
  }
  const Level<T>& last = cy.levels[depth - 1];
  coarse_solve<T>(cy.cinv, cy.cwork, last.r, nullptr, last.z, last.h * last.w);
  for (int64_t k = depth - 2; k >= 1; --k) {
    const Level<T>& L = cy.levels[k];
    up_pass<T, false>(L, L.r, nullptr, cy.omega, cy.zero, cy.levels[k + 1].z, L.z);
  }
  return up_pass<T, true>(fine, rs, cy.sq, cy.omega, cy.zero, cy.levels[1].z, zs);
}

// zs = D^1/2 B D^1/2 rs (B: one V-cycle) on the finest level; returns rs . zs.
template <typename T>
double apply_cycle(const Cycle<T>& cy, const T* rs, T* zs) {
  if (cy.levels.size() > 1) down_pass<T>(cy.levels[0], rs, cy.sq, cy.omega, cy.zero, cy.levels[1].r);
  return finish_cycle<T>(cy, rs, zs);
}

// ---- the CG passes on the scaled finest level (M = I - W') ----

// q = M p on one row (p: centre pc, above pu, below pd, zero rows where absent); returns p . q on the row
template <typename T>
__attribute__((noinline)) T matvec_row(const T* __restrict__ pc, const T* __restrict__ pu, const T* __restrict__ pd,
                                       const T* __restrict__ whr, const T* __restrict__ wu,
                                       const T* __restrict__ wd, T* __restrict__ q, int64_t w) {
  auto edge = [&](int64_t j) {
    T v = pc[j];
    if (j + 1 < w) v -= whr[j] * pc[j + 1];
    if (j > 0) v -= whr[j - 1] * pc[j - 1];
    v -= wd[j] * pd[j];
    v -= wu[j] * pu[j];
    q[j] = v;
    return v * pc[j];
  };
  T acc = edge(0);
  if (w > 1) acc += edge(w - 1);
#pragma omp simd reduction(+ : acc)
  for (int64_t j = 1; j < w - 1; ++j) {
    const T v = pc[j] - whr[j] * pc[j + 1] - whr[j - 1] * pc[j - 1] - wd[j] * pd[j] - wu[j] * pu[j];
    q[j] = v;
    acc += v * pc[j];
  }
  return acc;
}

// sum_j d_j a_j^2 on one row
template <typename T>
__attribute__((noinline)) T weighted_row(const T* __restrict__ d, const T* __restrict__ a, int64_t w) {
  T acc = 0;
#pragma omp simd reduction(+ : acc)
  for (int64_t j = 0; j < w; ++j) acc += d[j] * a[j] * a[j];
  return acc;
}

// out = p beta + z (first: z) on one row
template <typename T>
__attribute__((noinline)) void direction_row(const T* __restrict__ p, const T* __restrict__ z, T beta, bool first,
                                             T* __restrict__ out, int64_t w) {
  if (first) {
    std::copy(z, z + w, out);
    return;
  }
#pragma omp simd
  for (int64_t j = 0; j < w; ++j) out[j] = p[j] * beta + z[j];
}

// out = r - alpha q on one row; returns sum (s out)^2 (the residual's norm weighted by D = s^2) when kNorm
template <typename T, bool kNorm>
__attribute__((noinline)) T step_row(const T* __restrict__ r, const T* __restrict__ q, T alpha,
                                     const T* __restrict__ s, T* __restrict__ out, int64_t w) {
  T acc = 0;
#pragma omp simd reduction(+ : acc)
  for (int64_t j = 0; j < w; ++j) {
    const T v = r[j] - alpha * q[j];
    out[j] = v;
    if (kNorm) {
      const T sv = s[j] * v;
      acc += sv * sv;
    }
  }
  return acc;
}

// y += alpha p on one row
template <typename T>
__attribute__((noinline)) void axpy_row(T* __restrict__ y, const T* __restrict__ p, T alpha, int64_t w) {
#pragma omp simd
  for (int64_t j = 0; j < w; ++j) y[j] += alpha * p[j];
}

// The tasks of a pass over `blocks` blocks of rows: at most one per thread, at least `grain` blocks each; returns
// the first block of each task and the end.
std::vector<int64_t> task_bounds(int64_t blocks, int64_t grain) {
  const int64_t threads = std::max<int64_t>(1, at::get_num_threads());
  const int64_t tasks = std::max<int64_t>(1, std::min(threads, (blocks + grain - 1) / grain));
  const int64_t size = (blocks + tasks - 1) / tasks;
  std::vector<int64_t> bounds;
  for (int64_t b = 0; b < blocks; b += size) bounds.push_back(b);
  bounds.push_back(blocks);
  return bounds;
}

// Runs f(task, first block, end block) for the tasks of task_bounds, in parallel.
template <typename F>
void run_tasks(const std::vector<int64_t>& bounds, const F& f) {
  const int64_t tasks = static_cast<int64_t>(bounds.size()) - 1;
  at::parallel_for(0, tasks, 1, [&](int64_t a, int64_t b) {
    for (int64_t k = a; k < b; ++k) f(k, bounds[k], bounds[k + 1]);
  });
}

// Copies of the rows just outside each task's rows [i0, i1) of a (h, w) array (2 w per task: above, below): an
// array updated in place is read there through them, as it was before the pass.
template <typename T>
std::vector<T> halo_rows(const T* a, const std::vector<int64_t>& bounds, int64_t rows_per_block, int64_t h,
                         int64_t w) {
  const int64_t tasks = static_cast<int64_t>(bounds.size()) - 1;
  std::vector<T> halo(2 * tasks * w);
  for (int64_t k = 0; k < tasks; ++k) {
    const int64_t i0 = bounds[k] * rows_per_block, i1 = std::min(h, bounds[k + 1] * rows_per_block);
    if (i0 > 0) std::copy(a + (i0 - 1) * w, a + i0 * w, halo.data() + 2 * k * w);
    if (i1 < h) std::copy(a + i1 * w, a + (i1 + 1) * w, halo.data() + (2 * k + 1) * w);
  }
  return halo;
}

// One pass, in place: p = p beta + z (first: z), and returns p . M p (M: the finest level's scaled operator).
template <typename T>
double direction_matvec_pass(const Level<T> L, const T* z, T* p, T beta, bool first, const T* zero) {
  const int64_t h = L.h, w = L.w;
  const auto bounds = task_bounds(h, grain_rows(w));
  const std::vector<T> halo = halo_rows<T>(p, bounds, 1, h, w);
  const T* old = halo.data();
  std::vector<double> partial(h, 0.0);
  double* part = partial.data();
  run_tasks(bounds, [=](int64_t task, int64_t i0, int64_t i1) {
    std::vector<T> buf(4 * w);
    T* ring[3] = {buf.data(), buf.data() + w, buf.data() + 2 * w};
    T* q = buf.data() + 3 * w;
    auto make = [&](int64_t k) {
      const bool own = k >= i0 && k < i1;
      const T* pk = own ? p + k * w : old + (2 * task + (k < i0 ? 0 : 1)) * w;
      direction_row<T>(pk, z + k * w, beta, first, ring[k % 3], w);
      if (own) std::copy(ring[k % 3], ring[k % 3] + w, p + k * w);
    };
    if (i0 > 0) make(i0 - 1);
    make(i0);
    for (int64_t i = i0; i < i1; ++i) {
      if (i + 1 < h) make(i + 1);
      const bool up = i > 0, down = i + 1 < h;
      part[i] = static_cast<double>(matvec_row<T>(ring[i % 3], up ? ring[(i - 1) % 3] : zero,
                                                  down ? ring[(i + 1) % 3] : zero, L.wh + i * (w - 1),
                                                  up ? L.wv + (i - 1) * w : zero, down ? L.wv + i * w : zero, q, w));
    }
  });
  double total = 0.0;
  for (double v : partial) total += v;
  return total;
}

// One pass, in place: y += alpha p, r -= alpha M p, and, unless rc is null, the finest level's down pass of the
// V-cycle on the new r (block sums into rc); returns sum D r^2 of the new r (D = sq^2).
template <typename T>
double step_down_pass(const Level<T> L, T* r, const T* p, T* y, T alpha, const T* sq, T omega, const T* zero,
                      T* rc) {
  const int64_t h = L.h, w = L.w, fh = L.fh, fw = L.fw, w2 = L.w2;
  const bool down_too = rc != nullptr;
  const int64_t blocks = down_too ? L.h2 : h, rows_per_block = down_too ? fh : 1;
  const auto bounds = task_bounds(blocks, grain_rows(rows_per_block * w));
  const std::vector<T> halo = halo_rows<T>(r, bounds, rows_per_block, h, w);
  const T* old = halo.data();
  std::vector<double> partial(h, 0.0);
  double* part = partial.data();
  run_tasks(bounds, [=](int64_t task, int64_t c0, int64_t c1) {
    std::vector<T> buf(9 * w);
    T* rr[3] = {buf.data(), buf.data() + w, buf.data() + 2 * w};
    T* xr[3] = {buf.data() + 3 * w, buf.data() + 4 * w, buf.data() + 5 * w};
    T* q = buf.data() + 6 * w;
    T* t = buf.data() + 7 * w;
    T* acc = buf.data() + 8 * w;
    const int64_t i0 = c0 * rows_per_block, i1 = std::min(h, c1 * rows_per_block);
    auto make = [&](int64_t k) {  // the new r and x = omega r of row k
      const bool up = k > 0, down = k + 1 < h;
      matvec_row<T>(p + k * w, up ? p + (k - 1) * w : zero, down ? p + (k + 1) * w : zero, L.wh + k * (w - 1),
                    up ? L.wv + (k - 1) * w : zero, down ? L.wv + k * w : zero, q, w);
      if (k >= i0 && k < i1) {
        part[k] = static_cast<double>(step_row<T, true>(r + k * w, q, alpha, sq + k * w, rr[k % 3], w));
        std::copy(rr[k % 3], rr[k % 3] + w, r + k * w);
        axpy_row<T>(y + k * w, p + k * w, alpha, w);
      } else {
        step_row<T, false>(old + (2 * task + (k < i0 ? 0 : 1)) * w, q, alpha, sq + k * w, rr[k % 3], w);
      }
      if (down_too) smooth_row<T>(rr[k % 3], nullptr, omega, xr[k % 3], w);
    };
    if (!down_too) {
      for (int64_t k = i0; k < i1; ++k) make(k);
      return;
    }
    if (i0 > 0) make(i0 - 1);
    make(i0);
    for (int64_t i = i0; i < i1; ++i) {
      if (i + 1 < h) make(i + 1);
      const bool up = i > 0, down = i + 1 < h;
      residual_row<T, true>(rr[i % 3], nullptr, xr[i % 3], up ? xr[(i - 1) % 3] : zero,
                            down ? xr[(i + 1) % 3] : zero, L.wh + i * (w - 1), up ? L.wv + (i - 1) * w : zero,
                            down ? L.wv + i * w : zero, t, w);
      scale_row<T>(t, sq + i * w, w);
      restrict_row<T>(i, t, acc, rc, h, w, fh, fw, w2);
    }
  });
  double total = 0.0;
  for (double v : partial) total += v;
  return total;
}

// r = c - M y into r and sum D r^2
template <typename T>
double residual_pass(const T* y_, const T* c_, const T* dw_, const T* wh_, const T* wv_, const T* zero_, T* r_,
                     int64_t h, int64_t w) {
  return sum_rows(h, grain_rows(w), [=](int64_t i) {
    const bool up = i > 0, down = i + 1 < h;
    residual_row<T, true>(c_ + i * w, nullptr, y_ + i * w, up ? y_ + (i - 1) * w : zero_,
                          down ? y_ + (i + 1) * w : zero_, wh_ + i * (w - 1), up ? wv_ + (i - 1) * w : zero_,
                          down ? wv_ + i * w : zero_, r_ + i * w, w);
    return static_cast<double>(weighted_row<T>(dw_ + i * w, r_ + i * w, w));
  });
}

template <typename T>
double weighted_norm2(const T* dw_, const T* a_, int64_t h, int64_t w) {
  return sum_rows(h, grain_rows(w), [=](int64_t i) {
    return static_cast<double>(weighted_row<T>(dw_ + i * w, a_ + i * w, w));
  });
}

// Preconditioned CG on one grid, scaled form, as _cg_loop with check_every = 1: M y = c, y the start (in
// place: the result); out: iterations, the recurrence's relative residual at the last check, the true one.
// Three passes an iteration: p = z + beta p with p . M p; y += alpha p and r -= alpha M p with the V-cycle's
// first down pass; the rest of the V-cycle (z and r . z). work: 3 n of T.
template <typename T>
void pcg_one(const Cycle<T>& cy, const T* c, const T* dw, T* y, T* work, int64_t h, int64_t w, double rtol,
             int64_t max_iter, bool start_zero, double* out) {
  const Level<T>& fine = cy.levels[0];
  const int64_t n = h * w;
  T* r = work;
  T* p = work + n;
  T* z = work + 2 * n;
  T* rc = cy.levels.size() > 1 ? cy.levels[1].r : nullptr;
  const double tiny = static_cast<double>(std::numeric_limits<T>::min());
  double res = 0.0;
  if (start_zero) {
    std::fill(y, y + n, T(0));
    std::copy(c, c + n, r);
    res = std::sqrt(weighted_norm2<T>(dw, r, h, w));
  } else {
    res = std::sqrt(residual_pass<T>(y, c, dw, fine.wh, fine.wv, cy.zero, r, h, w));
  }
  const double b_norm = std::sqrt(weighted_norm2<T>(dw, c, h, w));
  const double threshold = rtol * b_norm;
  auto relative = [&](double v) {  // NaN when the norm of b is (a broken, numerically singular system)
    return b_norm > 0 ? v / std::max(b_norm, std::numeric_limits<double>::min()) : (std::isnan(b_norm) ? b_norm : 0.0);
  };
  int64_t iterations = 0;
  double rel = relative(res);
  if (res > threshold && std::isfinite(res) && max_iter > 0) {
    double rz = apply_cycle<T>(cy, r, z);
    double beta = 0.0;
    for (int64_t it = 1; it <= max_iter; ++it) {
      const double pq = direction_matvec_pass<T>(fine, z, p, static_cast<T>(beta), it == 1, cy.zero);
      const double alpha = rz / std::max(pq, tiny);
      res = std::sqrt(step_down_pass<T>(fine, r, p, y, static_cast<T>(alpha), cy.sq, cy.omega, cy.zero, rc));
      rel = relative(res);
      iterations = it;
      if (!(res > threshold) || !std::isfinite(res)) break;
      const double rz_new = finish_cycle<T>(cy, r, z);
      beta = rz_new / std::max(rz, tiny);
      rz = rz_new;
    }
  }
  const double true_res = std::sqrt(residual_pass<T>(y, c, dw, fine.wh, fine.wv, cy.zero, z, h, w));
  out[0] = static_cast<double>(iterations);
  out[1] = rel;
  out[2] = relative(true_res);
}

void check_cpu(const torch::Tensor& t, const torch::Tensor& like, const char* name) {
  TORCH_CHECK(t.device().is_cpu() && t.is_contiguous(), name, ": expected contiguous CPU tensors");
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), name, ": expected tensors of one dtype");
}

// The cycle's tensors, checked: levels is [dg, jac, wh, wv] of levels 1, 2, ... (B, h, w) each; the coarsest
// (whose arrays are not read) last.
struct CycleTensors {
  std::vector<torch::Tensor> levels;
  torch::Tensor cinv, r, z, zero, cwork;
  int64_t depth = 1, g = 1, h = 1, w = 1;
};

CycleTensors prepare(const torch::Tensor& wh, const torch::Tensor& wv, const torch::Tensor& like,
                     const std::vector<torch::Tensor>& levels, const torch::Tensor& cinv, const char* name) {
  CycleTensors ct;
  check_cpu(wh, like, name);
  check_cpu(wv, like, name);
  TORCH_CHECK(levels.size() % 4 == 0, name, ": levels must hold (dg, jac, wh, wv) per level");
  for (const auto& t : levels) check_cpu(t, like, name);
  TORCH_CHECK(cinv.device().is_cpu() && cinv.is_contiguous() && cinv.scalar_type() == torch::kFloat64, name,
              ": expected a contiguous float64 coarse inverse");
  ct.levels = levels;
  ct.cinv = cinv;
  ct.g = wh.size(0);
  ct.h = wh.size(1);
  ct.w = wh.size(2) + 1;
  ct.depth = 1 + static_cast<int64_t>(levels.size() / 4);
  int64_t cells = 0, widest = ct.w;
  for (int64_t k = 1; k < ct.depth; ++k) {
    const auto& dg = levels[4 * (k - 1)];
    cells += dg.size(1) * dg.size(2);
    widest = std::max<int64_t>(widest, dg.size(2));
  }
  const int64_t m = cinv.size(1);
  ct.r = torch::empty({std::max<int64_t>(cells, 1)}, like.options());
  ct.z = torch::empty({std::max<int64_t>(cells, 1)}, like.options());
  ct.zero = torch::zeros({widest}, like.options());
  ct.cwork = torch::empty({m}, like.options().dtype(torch::kFloat64));
  return ct;
}

// The Cycle of grid k of the batch over ct's tensors; wh, wv the scaled finest weights, sq its D^1/2 rows.
template <typename T>
Cycle<T> cycle_of(const CycleTensors& ct, const torch::Tensor& wh, const torch::Tensor& wv, const torch::Tensor& sq,
                  int64_t k, double omega) {
  Cycle<T> cy;
  cy.omega = static_cast<T>(omega);
  cy.zero = ct.zero.data_ptr<T>();
  cy.sq = sq.data_ptr<T>() + k * ct.h * ct.w;
  const int64_t m = ct.cinv.size(1);
  cy.cinv = ct.cinv.data_ptr<double>() + k * m * m;
  cy.cwork = ct.cwork.data_ptr<double>();
  Level<T> fine;
  fine.h = ct.h;
  fine.w = ct.w;
  fine.wh = wh.data_ptr<T>() + k * ct.h * (ct.w - 1);
  fine.wv = wv.data_ptr<T>() + k * (ct.h - 1) * ct.w;
  cy.levels.push_back(fine);
  int64_t offset = 0;
  for (int64_t l = 1; l < ct.depth; ++l) {
    const auto* t = &ct.levels[4 * (l - 1)];
    Level<T> L;
    L.h = t[0].size(1);
    L.w = t[0].size(2);
    L.dg = t[0].data_ptr<T>() + k * L.h * L.w;
    L.jac = t[1].data_ptr<T>() + k * L.h * L.w;
    L.wh = t[2].data_ptr<T>() + k * L.h * (L.w - 1);
    L.wv = t[3].data_ptr<T>() + k * (L.h - 1) * L.w;
    L.r = ct.r.data_ptr<T>() + offset;
    L.z = ct.z.data_ptr<T>() + offset;
    offset += L.h * L.w;
    cy.levels.push_back(L);
  }
  for (auto& L : cy.levels) {  // the 2 x 2 aggregation (2 x 1, 1 x 2 once a side is one pixel wide)
    L.fh = L.h > 1 ? 2 : 1;
    L.fw = L.w > 1 ? 2 : 1;
    L.h2 = (L.h + L.fh - 1) / L.fh;
    L.w2 = (L.w + L.fw - 1) / L.fw;
  }
  const Level<T>& last = cy.levels.back();
  TORCH_CHECK(m == last.h * last.w, "multigrid: the coarse inverse does not fit the coarsest level");
  for (size_t l = 1; l < cy.levels.size(); ++l) {
    TORCH_CHECK(cy.levels[l].h == cy.levels[l - 1].h2 && cy.levels[l].w == cy.levels[l - 1].w2,
                "multigrid: a level is not the 2 x 2 aggregation of the one above");
  }
  return cy;
}

}  // namespace mg

// One V-cycle of the scaled preconditioner on (G, H*W) rows rs: D^1/2 B D^1/2 rs, and (G,) float64 rs . zs.
std::vector<torch::Tensor> grid_mg_precondition(torch::Tensor wh, torch::Tensor wv, torch::Tensor sq,
                                                torch::Tensor rs, std::vector<torch::Tensor> levels,
                                                torch::Tensor cinv, double omega) {
  mg::check_cpu(sq, rs, "grid_mg_precondition");
  mg::check_cpu(rs, rs, "grid_mg_precondition");
  auto ct = mg::prepare(wh, wv, rs, levels, cinv, "grid_mg_precondition");
  auto zs = torch::empty_like(rs);
  auto dots = torch::empty({ct.g}, rs.options().dtype(torch::kFloat64));
  AT_DISPATCH_FLOATING_TYPES(rs.scalar_type(), "grid_mg_precondition", [&] {
    for (int64_t k = 0; k < ct.g; ++k) {
      const auto cy = mg::cycle_of<scalar_t>(ct, wh, wv, sq, k, omega);
      const int64_t o = k * ct.h * ct.w;
      dots.data_ptr<double>()[k] =
          mg::apply_cycle<scalar_t>(cy, rs.data_ptr<scalar_t>() + o, zs.data_ptr<scalar_t>() + o);
    }
  });
  return {zs, dots};
}

// Multigrid-preconditioned CG on G pixel grids in the scaled form of crfdepth/linalg/cg.py (as grid_cg of
// kernels.cpp, with z = D^1/2 B D^1/2 r and a convergence check after every iteration): (G, H, W-1) wh and
// (G, H-1, W) wv the scaled weights, (G, H*W) c, residual weights dw (D), sq (D^1/2), start y (in place: the
// result; start_zero: from 0). Returns (G, 3) float64: iterations, the recurrence's relative residual at the
// last check, the true relative residual of the result.
torch::Tensor grid_mg_cg(torch::Tensor wh, torch::Tensor wv, torch::Tensor c, torch::Tensor dw, torch::Tensor sq,
                         torch::Tensor y, std::vector<torch::Tensor> levels, torch::Tensor cinv, double omega,
                         double rtol, int64_t max_iter, bool start_zero) {
  for (auto* t : {&c, &dw, &sq, &y}) mg::check_cpu(*t, c, "grid_mg_cg");
  auto ct = mg::prepare(wh, wv, c, levels, cinv, "grid_mg_cg");
  const int64_t h = ct.h, w = ct.w, n = h * w;
  auto out = torch::empty({ct.g, 3}, c.options().dtype(torch::kFloat64));
  auto work = torch::empty({3 * n}, c.options());
  AT_DISPATCH_FLOATING_TYPES(c.scalar_type(), "grid_mg_cg", [&] {
    using T = scalar_t;
    for (int64_t k = 0; k < ct.g; ++k) {
      const auto cy = mg::cycle_of<T>(ct, wh, wv, sq, k, omega);
      const int64_t o = k * n;
      mg::pcg_one<T>(cy, c.data_ptr<T>() + o, dw.data_ptr<T>() + o, y.data_ptr<T>() + o, work.data_ptr<T>(), h, w,
                     rtol, max_iter, start_zero, out.data_ptr<double>() + 3 * k);
    }
  });
  return out;
}

}  // namespace

void register_multigrid(pybind11::module& m) {
  m.def("grid_mg_precondition", &grid_mg_precondition, "one multigrid V-cycle, scaled preconditioner form");
  m.def("grid_mg_cg", &grid_mg_cg, "multigrid-preconditioned CG on pixel grids, scaled form");
}

}  // namespace crfdepth_multigrid
