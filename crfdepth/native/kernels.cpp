// Fused CPU kernels of crfdepth (docs/design.md section 4b). Each function does in one pass over
// memory what the eager path (crfdepth/linalg/cg.py) does in several
// torch kernels; the eager path is the reference the tests compare against.
//
// Built on first use by crfdepth/native/__init__.py, as one translation unit with the parts it includes. Threads:
// at::parallel_for, i.e. torch's intra-op pool and torch.get_num_threads().

#include <torch/extension.h>
#include <ATen/Parallel.h>

// The other kernels, each in its own namespace: one translation unit, so torch's headers are parsed once
// (each further unit cost about 24 s of the first build).
#include "multigrid.h"
#include "nearest.h"
#include "potentials.h"
#include "predictive_std.h"
#include "workspace.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace {

constexpr int64_t kGrain = 16;  // rows per task at least

// Partial sums of row blocks, added in block order: the result does not depend on the thread count.
// The lambdas below copy their pointers into __restrict__ locals: through captured references the
// compiler must assume every store may change a pointer, and does not vectorise.
template <typename F>
double sum_over_rows(int64_t rows, F&& row_sum) {
  std::vector<double> partial(rows, 0.0);
  at::parallel_for(0, rows, kGrain, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) partial[r] = row_sum(r);
  });
  double total = 0.0;
  for (double v : partial) total += v;
  return total;
}

constexpr int64_t kChunk = 4096;  // entries per block of the element-wise passes

// The interior of a row (columns 1 .. w-2, both vertical neighbours present) of the passes below, as
// separate noinline functions with __restrict__ arguments: inlined into the tasks' lambdas (the OpenMP
// outlined function of at::parallel_for), GCC left these `omp simd reduction` loops scalar.
// q = M p on the row and the sum of p q.
template <typename T>
__attribute__((noinline)) T matvec_dot_row(const T* __restrict__ pr, const T* __restrict__ whr,
                                           const T* __restrict__ down, const T* __restrict__ wd,
                                           const T* __restrict__ up, const T* __restrict__ wu, T* __restrict__ qr,
                                           int64_t w) {
  T acc = 0;
#pragma omp simd reduction(+ : acc)
  for (int64_t j = 1; j < w - 1; ++j) {
    const T v = pr[j] - whr[j] * pr[j + 1] - whr[j - 1] * pr[j - 1] - wd[j] * down[j] - wu[j] * up[j];
    qr[j] = v;
    acc += v * pr[j];
  }
  return acc;
}

// r = c - M y on the row and the sum of D r^2.
template <typename T>
__attribute__((noinline)) T residual_row(const T* __restrict__ yr, const T* __restrict__ whr,
                                         const T* __restrict__ down, const T* __restrict__ wd,
                                         const T* __restrict__ up, const T* __restrict__ wu, const T* __restrict__ cr,
                                         const T* __restrict__ dwr, T* __restrict__ rr, int64_t w) {
  T acc = 0;
#pragma omp simd reduction(+ : acc)
  for (int64_t j = 1; j < w - 1; ++j) {
    const T t = cr[j] - (yr[j] - whr[j] * yr[j + 1] - whr[j - 1] * yr[j - 1] - wd[j] * down[j] - wu[j] * up[j]);
    rr[j] = t;
    acc += dwr[j] * t * t;
  }
  return acc;
}

// One pass over an H x W grid applying M = I - W' (scaled weights wh (H, W-1), wv (H-1, W)) to p,
// row by row: emit(e, v) receives (M p)_e at flat index e of a border pixel, stores what it needs and
// returns a term of the sum this returns; interior(i, row pointers) does a row's interior (one of the
// row functions above). Sums in T within a row, in double over rows.
template <typename T, typename Emit, typename Interior>
double stencil_pass(const T* p_, const T* wh_, const T* wv_, int64_t h, int64_t w, Emit emit, Interior interior) {
  return sum_over_rows(h, [=](int64_t i) {
    const T* __restrict__ pr = p_ + i * w;
    const T* __restrict__ whr = wh_ + i * (w - 1);
    const T* __restrict__ down = i + 1 < h ? p_ + (i + 1) * w : nullptr;
    const T* __restrict__ wd = i + 1 < h ? wv_ + i * w : nullptr;
    const T* __restrict__ up = i > 0 ? p_ + (i - 1) * w : nullptr;
    const T* __restrict__ wu = i > 0 ? wv_ + (i - 1) * w : nullptr;
    const int64_t row = i * w;
    auto edge = [&](int64_t j) {  // a pixel with a neighbour missing
      T v = pr[j];
      if (j + 1 < w) v -= whr[j] * pr[j + 1];
      if (j > 0) v -= whr[j - 1] * pr[j - 1];
      if (down) v -= wd[j] * down[j];
      if (up) v -= wu[j] * up[j];
      return emit(row + j, v);
    };
    T acc = edge(0);
    if (w > 1) acc += edge(w - 1);
    if (down && up) {
      acc += interior(i, pr, whr, down, wd, up, wu);
    } else {
      for (int64_t j = 1; j < w - 1; ++j) acc += edge(j);
    }
    return static_cast<double>(acc);
  });
}

// q = M p and p . q.
template <typename T>
double grid_matvec_dot_one(const T* p, const T* wh, const T* wv, T* q, int64_t h, int64_t w) {
  return stencil_pass<T>(
      p, wh, wv, h, w, [=](int64_t e, T v) { q[e] = v; return v * p[e]; },
      [=](int64_t i, const T* pr, const T* whr, const T* down, const T* wd, const T* up, const T* wu) {
        return matvec_dot_row<T>(pr, whr, down, wd, up, wu, q + i * w, w);
      });
}

// r = c - M y and sum D r^2.
template <typename T>
double residual_one(const T* y, const T* wh, const T* wv, const T* c, const T* dw, T* r, int64_t h, int64_t w) {
  return stencil_pass<T>(
      y, wh, wv, h, w,
      [=](int64_t e, T v) {
        const T t = c[e] - v;
        r[e] = t;
        return dw[e] * t * t;
      },
      [=](int64_t i, const T* yr, const T* whr, const T* down, const T* wd, const T* up, const T* wu) {
        return residual_row<T>(yr, whr, down, wd, up, wu, c + i * w, dw + i * w, r + i * w, w);
      });
}

// y += alpha p, r -= alpha q over n entries; returns r . r after the update.
template <typename T>
double update_one(T* y_, T* r_, const T* p_, const T* q_, T alpha, int64_t n) {
  return sum_over_rows((n + kChunk - 1) / kChunk, [=](int64_t b) {
    T* __restrict__ y = y_;
    T* __restrict__ r = r_;
    const T* __restrict__ p = p_;
    const T* __restrict__ q = q_;
    const int64_t lo = b * kChunk, hi = std::min(n, lo + kChunk);
    T acc = 0;
#pragma omp simd reduction(+ : acc)
    for (int64_t k = lo; k < hi; ++k) {
      y[k] += alpha * p[k];
      const T v = r[k] - alpha * q[k];
      r[k] = v;
      acc += v * v;
    }
    return static_cast<double>(acc);
  });
}

// p = r + beta p over n entries.
template <typename T>
void direction_one(T* p_, const T* r_, T beta, int64_t n) {
  at::parallel_for(0, n, kChunk, [=](int64_t lo, int64_t hi) {
    T* __restrict__ p = p_;
    const T* __restrict__ r = r_;
#pragma omp simd
    for (int64_t k = lo; k < hi; ++k) p[k] = r[k] + beta * p[k];
  });
}

// sum_k a_k b_k over n entries.
template <typename T>
double dot_sum(const T* a_, const T* b_, int64_t n) {
  return sum_over_rows((n + kChunk - 1) / kChunk, [=](int64_t blk) {
    const T* __restrict__ a = a_;
    const T* __restrict__ b = b_;
    const int64_t lo = blk * kChunk, hi = std::min(n, lo + kChunk);
    T acc = 0;
#pragma omp simd reduction(+ : acc)
    for (int64_t k = lo; k < hi; ++k) acc += a[k] * b[k];
    return static_cast<double>(acc);
  });
}

// sum_k d_k a_k^2 over n entries (a norm weighted by D).
template <typename T>
double weighted_squares(const T* d_, const T* a_, int64_t n) {
  return sum_over_rows((n + kChunk - 1) / kChunk, [=](int64_t blk) {
    const T* __restrict__ d = d_;
    const T* __restrict__ a = a_;
    const int64_t lo = blk * kChunk, hi = std::min(n, lo + kChunk);
    T acc = 0;
#pragma omp simd reduction(+ : acc)
    for (int64_t k = lo; k < hi; ++k) acc += d[k] * a[k] * a[k];
    return static_cast<double>(acc);
  });
}

void check_rows(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu() && t.is_contiguous(), name, ": expected a contiguous CPU tensor");
}

}  // namespace

// Jacobi-preconditioned CG on G pixel grids, in the scaled form of crfdepth/linalg/cg.py: solves
// M y = c with M = I - W' (scaled weights wh, wv), y holding the start and receiving the result; the
// convergence test every check_every iterations is sqrt(sum D r^2) <= rtol sqrt(sum D c^2) on the
// recurrence's residual, as the eager loop's. Three passes per iteration. Returns (G, 3) float64:
// iterations, the recurrence's relative residual at the last check, and the true relative residual
// of the result, sqrt(sum D (c - M y)^2) / sqrt(sum D c^2).
template <typename T>
void grid_cg_one(const T* wh, const T* wv, const T* c, const T* dw, T* y, T* r, T* p, T* q, int64_t h, int64_t w,
                 double rtol, int64_t max_iter, int64_t check_every, bool start_zero, double* out) {
  const int64_t n = h * w;
  const double tiny = std::numeric_limits<double>::min();
  double res = 0.0;
  if (start_zero) {
    std::fill(y, y + n, T(0));
    std::copy(c, c + n, r);
    res = std::sqrt(weighted_squares<T>(dw, r, n));
  } else {
    res = std::sqrt(residual_one<T>(y, wh, wv, c, dw, r, h, w));
  }
  const double b_norm = std::sqrt(weighted_squares<T>(dw, c, n));
  const double threshold = rtol * b_norm;
  auto relative = [&](double v) {  // NaN when the norm of b is (a broken, numerically singular system)
    return b_norm > 0 ? v / std::max(b_norm, tiny) : (std::isnan(b_norm) ? b_norm : 0.0);
  };
  int64_t iterations = 0;
  double rel = relative(res);
  if (res > threshold && std::isfinite(res) && max_iter > 0) {
    std::copy(r, r + n, p);
    double rz = dot_sum<T>(r, r, n);
    for (int64_t it = 1; it <= max_iter; ++it) {
      const double pq = grid_matvec_dot_one<T>(p, wh, wv, q, h, w);
      const double alpha = rz / std::max(pq, tiny);
      const double rr = update_one<T>(y, r, p, q, static_cast<T>(alpha), n);
      if (it % check_every == 0 || it == max_iter) {
        res = std::sqrt(weighted_squares<T>(dw, r, n));
        rel = relative(res);
        iterations = it;
        if (!(res > threshold) || !std::isfinite(res)) break;
      }
      const double beta = rr / std::max(rz, tiny);
      rz = rr;
      direction_one<T>(p, r, static_cast<T>(beta), n);
    }
  }
  const double true_res = std::sqrt(residual_one<T>(y, wh, wv, c, dw, q, h, w));  // in q: r is the recurrence's
  out[0] = static_cast<double>(iterations);
  out[1] = rel;
  out[2] = relative(true_res);
}

// (G, H, W-1) wh, (G, H-1, W) wv, (G, H*W) c, residual weights dw, start y (in place: the result);
// start_zero: ignore y's values and start from 0.
torch::Tensor grid_cg(torch::Tensor wh, torch::Tensor wv, torch::Tensor c, torch::Tensor dw, torch::Tensor y,
                      double rtol, int64_t max_iter, int64_t check_every, bool start_zero) {
  for (auto* t : {&wh, &wv, &c, &dw, &y}) check_rows(*t, "grid_cg");
  const int64_t g = wh.size(0), h = wh.size(1), w = wh.size(2) + 1;
  auto out = torch::empty({g, 3}, c.options().dtype(torch::kFloat64));
  auto r = torch::empty_like(c), p = torch::empty_like(c), q = torch::empty_like(c);
  AT_DISPATCH_FLOATING_TYPES(c.scalar_type(), "grid_cg", [&] {
    for (int64_t k = 0; k < g; ++k) {
      const int64_t o = k * h * w;
      grid_cg_one<scalar_t>(wh.data_ptr<scalar_t>() + k * h * (w - 1), wv.data_ptr<scalar_t>() + k * (h - 1) * w,
                            c.data_ptr<scalar_t>() + o, dw.data_ptr<scalar_t>() + o, y.data_ptr<scalar_t>() + o,
                            r.data_ptr<scalar_t>() + o, p.data_ptr<scalar_t>() + o, q.data_ptr<scalar_t>() + o, h, w,
                            rtol, max_iter, check_every, start_zero, out.data_ptr<double>() + 3 * k);
    }
  });
  return out;
}

// One grid of grid_solve (outside the dispatch macro: a #pragma cannot stand in a macro's argument).
template <typename T>
void grid_solve_one(const T* dk, const T* bk, const T* whk, const T* wvk, const T* x0k, T* xk, T* sv, T* dwv, T* cv,
                    T* yv, T* whs_k, T* wvs_k, T* r, T* p, T* q, int64_t h, int64_t w, double rtol, int64_t max_iter,
                    int64_t check_every, int64_t restarts, double* st) {
  const bool warm = x0k != nullptr;
  const int64_t n = h * w;
  // D = d + degree, s = D^-1/2, and the largest |b_i| of each row
  std::vector<double> peaks(h, 0.0);
  at::parallel_for(0, h, kGrain, [=, &peaks](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const T* __restrict__ di = dk + i * w;
      const T* __restrict__ bi = bk + i * w;
      const T* __restrict__ whr = whk + i * (w - 1);
      T* __restrict__ deg = dwv + i * w;
      T* __restrict__ si = sv + i * w;
      T row_peak = 0;
      for (int64_t j = 0; j < w; ++j) deg[j] = di[j];
      for (int64_t j = 0; j < w - 1; ++j) deg[j] += whr[j];
      for (int64_t j = 1; j < w; ++j) deg[j] += whr[j - 1];
      if (i + 1 < h) {
        const T* __restrict__ wd = wvk + i * w;
        for (int64_t j = 0; j < w; ++j) deg[j] += wd[j];
      }
      if (i > 0) {
        const T* __restrict__ wu = wvk + (i - 1) * w;
        for (int64_t j = 0; j < w; ++j) deg[j] += wu[j];
      }
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) si[j] = T(1) / std::sqrt(deg[j]);
#pragma omp simd reduction(max : row_peak)
      for (int64_t j = 0; j < w; ++j) row_peak = std::max(row_peak, std::abs(bi[j]));
      peaks[i] = static_cast<double>(row_peak);
    }
  });
  const double peak = *std::max_element(peaks.begin(), peaks.end());
  if (peak == 0.0) {  // b = 0: x = 0 exactly
    std::fill(xk, xk + n, T(0));
    st[2] = 1.0;
    return;
  }
  int exponent = 0;
  std::frexp(peak, &exponent);
  const double scale = std::ldexp(1.0, exponent);  // dividing by it is exact
  const T inv_scale = static_cast<T>(1.0 / scale);
  // the scaled weights, right-hand side and start
  at::parallel_for(0, h, kGrain, [=](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const T* __restrict__ si = sv + i * w;
      const T* __restrict__ whr = whk + i * (w - 1);
      T* __restrict__ out_h = whs_k + i * (w - 1);
#pragma omp simd
      for (int64_t j = 0; j < w - 1; ++j) out_h[j] = whr[j] * si[j] * si[j + 1];
      if (i + 1 < h) {
        const T* __restrict__ sd = sv + (i + 1) * w;
        const T* __restrict__ wd = wvk + i * w;
        T* __restrict__ out_v = wvs_k + i * w;
#pragma omp simd
        for (int64_t j = 0; j < w; ++j) out_v[j] = wd[j] * si[j] * sd[j];
      }
      const T* __restrict__ bi = bk + i * w;
      T* __restrict__ ci = cv + i * w;
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) ci[j] = (bi[j] * inv_scale) * si[j];
      if (x0k != nullptr) {
        const T* __restrict__ xi = x0k + i * w;
        T* __restrict__ yi = yv + i * w;
#pragma omp simd
        for (int64_t j = 0; j < w; ++j) yi[j] = (xi[j] * inv_scale) / si[j];
      }
    }
  });
  int64_t total = 0;
  double out[3] = {0.0, 0.0, 0.0};
  bool start_zero = !warm;
  for (int64_t attempt = 0; attempt <= restarts; ++attempt) {
    grid_cg_one<T>(whs_k, wvs_k, cv, dwv, yv, r, p, q, h, w, rtol,
                   max_iter - total, check_every, start_zero, out);
    start_zero = false;
    total += static_cast<int64_t>(out[0]);
    const bool recurrence_met = out[1] <= rtol && std::isfinite(out[1]);
    if (out[2] <= rtol || total >= max_iter || !recurrence_met) break;
  }
  // x = D^-1/2 y, scaled back; is it finite?
  const T t_scale = static_cast<T>(scale);
  std::vector<char> finite(h, 1);
  at::parallel_for(0, h, kGrain, [=, &finite](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const T* __restrict__ yi = yv + i * w;
      const T* __restrict__ si = sv + i * w;
      T* __restrict__ xi = xk + i * w;
      T bad = 0;
#pragma omp simd reduction(+ : bad)
      for (int64_t j = 0; j < w; ++j) {
        const T v = yi[j] * si[j] * t_scale;
        xi[j] = v;
        bad += v - v;  // NaN where v is NaN or infinite, else 0
      }
      finite[i] = bad == 0;
    }
  });
  st[0] = static_cast<double>(total);
  st[1] = out[2];
  st[2] = std::all_of(finite.begin(), finite.end(), [](char f) { return f != 0; }) ? 1.0 : 0.0;
}

// The whole undifferentiated solve of (diag(d) + L(wh, wv)) x = b on G pixel grids, as
// crfdepth/linalg/adjoint.py's _krylov_solve does it in torch: b scaled by the power of two above its
// largest |b_i| (exact), the Jacobi scaling M = D^-1/2 A D^-1/2 with D = d + degree, grid_cg_one,
// restarts from the true residual, and x = D^-1/2 y scaled back. Two passes before the iterations
// and one after, instead of about twenty. x0 may be undefined (start from 0). Returns x and (G, 3)
// float64: iterations, the true relative residual ||b - A x|| / ||b||, and 1 where x is finite.
std::vector<torch::Tensor> grid_solve(torch::Tensor d, torch::Tensor b, torch::Tensor wh, torch::Tensor wv,
                                      c10::optional<torch::Tensor> x0, double rtol, int64_t max_iter,
                                      int64_t check_every, int64_t restarts) {
  for (auto* t : {&d, &b, &wh, &wv}) check_rows(*t, "grid_solve");
  const int64_t g = b.size(0), h = b.size(1), w = b.size(2), n = h * w;
  const bool warm = x0.has_value() && x0->defined();
  if (warm) check_rows(*x0, "grid_solve");
  auto x = torch::empty_like(b);
  auto stats = torch::zeros({g, 3}, b.options().dtype(torch::kFloat64));
  // one frame's scratch, frame after frame: the scaled weights, s, D, c, y, r, p, q (nine planes)
  auto work = crfdepth_workspace::scratch(crfdepth_workspace::kGridSolve, 9 * n, b.scalar_type());
  AT_DISPATCH_FLOATING_TYPES(b.scalar_type(), "grid_solve", [&] {
    using T = scalar_t;
    T* plane[9];
    for (int k = 0; k < 9; ++k) plane[k] = work.data_ptr<T>() + k * n;
    for (int64_t k = 0; k < g; ++k) {
      grid_solve_one<T>(d.data_ptr<T>() + k * n, b.data_ptr<T>() + k * n, wh.data_ptr<T>() + k * h * (w - 1),
                        wv.data_ptr<T>() + k * (h - 1) * w, warm ? x0->data_ptr<T>() + k * n : nullptr,
                        x.data_ptr<T>() + k * n, plane[0], plane[1], plane[2], plane[3], plane[4], plane[5],
                        plane[6], plane[7], plane[8], h, w, rtol, max_iter, check_every, restarts,
                        stats.data_ptr<double>() + 3 * k);
    }
  });
  return {x, stats};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  crfdepth_multigrid::register_multigrid(m);
  crfdepth_potentials::register_potentials(m);
  crfdepth_nearest::register_nearest(m);
  crfdepth_predictive_std::register_std(m);
  m.def("grid_cg", &grid_cg, "Jacobi-preconditioned CG on pixel grids, scaled form");
  m.def("grid_solve", &grid_solve, "the whole Jacobi-preconditioned CG solve on pixel grids");
}
