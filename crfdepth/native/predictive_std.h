// The predictive std of the pixel grid in two passes (docs/design.md sections 5 and 4b): what
// crfdepth/uncertainty/predictive.py (std_features, predictive_std, PredictiveStd) and
// crfdepth/uncertainty/posterior.py (grid_conditional_variance) compute with about 40 torch kernels
// when no gradient is needed, with the same formulas and order of operations.
//
// Pass 1 (per row): log z and the gate disagreement ``behind``, and their window maxima and minima
// along the row. Pass 2 (per row): the same down the columns, the conditional variance 1 / A_ii, the
// five signals and the std. The logarithms and the exponential are torch's
// own vectorised ones (at::vec, SLEEF where the build has AVX2).

#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "vec_math.h"
#include "workspace.h"

namespace crfdepth_predictive_std {

namespace {

constexpr int64_t kRows = 8;  // rows per task at least

using crfdepth_vec::exp_inplace;
using crfdepth_vec::log_inplace;

// out[j] = max (or min) of x[j - r .. j + r] within [0, n): a sliding window along one row (the
// interior by shifted passes, which vectorise; the borders one by one).
template <typename T, bool kMax>
void row_window(const T* __restrict__ x, T* __restrict__ out, int64_t n, int64_t r) {
  auto border = [&](int64_t j) {
    const int64_t a = std::max<int64_t>(0, j - r), b = std::min<int64_t>(n - 1, j + r);
    T m = x[a];
    for (int64_t k = a + 1; k <= b; ++k) m = kMax ? std::max(m, x[k]) : std::min(m, x[k]);
    out[j] = m;
  };
  if (n <= 2 * r) {
    for (int64_t j = 0; j < n; ++j) border(j);
    return;
  }
  for (int64_t j = 0; j < r; ++j) border(j);
  for (int64_t j = n - r; j < n; ++j) border(j);
  const int64_t m = n - 2 * r;  // out[r .. n - r) from x shifted by 0 .. 2r
  T* __restrict__ o = out + r;
  std::copy(x, x + m, o);
  for (int64_t k = 1; k <= 2 * r; ++k) {
    const T* __restrict__ xs = x + k;
#pragma omp simd
    for (int64_t j = 0; j < m; ++j) o[j] = kMax ? std::max(o[j], xs[j]) : std::min(o[j], xs[j]);
  }
}

// out[j] = max (or min) over rows i - r .. i + r (within [0, h)) of rows[.][j].
template <typename T, bool kMax>
void column_window(const T* base, T* __restrict__ out, int64_t i, int64_t h, int64_t w, int64_t r) {
  const int64_t a = std::max<int64_t>(0, i - r), b = std::min<int64_t>(h - 1, i + r);
  std::copy(base + a * w, base + (a + 1) * w, out);
  for (int64_t k = a + 1; k <= b; ++k) {
    const T* __restrict__ row = base + k * w;
#pragma omp simd
    for (int64_t j = 0; j < w; ++j) out[j] = kMax ? std::max(out[j], row[j]) : std::min(out[j], row[j]);
  }
}

template <typename T>
void std_frame(const T* z, const T* sparse, const T* gate, const T* dist, const T* d, const T* wh, const T* wv,
               int power, const double* c, double noise, int64_t edge_r, int64_t lidar_r, int64_t h, int64_t w,
               T* std_out, T* features, T* lx, T* hi, T* lo, T* hb) {
  const int64_t n = h * w;
  // Pass 1: log x = log(max(z, 1e-3)) and behind = max(log(max(s, 1e-3)) - log x, 0) (1 - g) [s > 0] (its
  // log only on the returns: elsewhere the product is 0), then the windows along each row.
  at::parallel_for(0, h, kRows, [=](int64_t i0, int64_t i1) {
    std::vector<T> row(w);
    T* __restrict__ bi = row.data();
    for (int64_t i = i0; i < i1; ++i) {
      const T* __restrict__ zi = z + i * w;
      const T* __restrict__ si = sparse + i * w;
      T* __restrict__ li = lx + i * w;
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) li[j] = std::max(zi[j], T(1e-3));
      log_inplace(li, w);
      row_window<T, true>(li, hi + i * w, w, edge_r);
      row_window<T, false>(li, lo + i * w, w, edge_r);
      if (gate == nullptr) {
        std::fill(hb + i * w, hb + (i + 1) * w, T(0));
        continue;
      }
      const T* __restrict__ gi = gate + i * w;
      for (int64_t j = 0; j < w; ++j)
        bi[j] = si[j] > T(0) ? std::max(std::log(std::max(si[j], T(1e-3))) - li[j], T(0)) * (T(1) - gi[j]) : T(0);
      row_window<T, true>(bi, hb + i * w, w, lidar_r);
    }
  });
  // Pass 2: the windows down the columns, the signals and the std.
  const T c0 = T(c[0]), c1 = T(c[1]), c2 = T(c[2]), c3 = T(c[3]), c4 = T(c[4]), c5 = T(c[5]);
  const T noise2 = T(noise * noise);
  at::parallel_for(0, h, kRows, [=](int64_t i0, int64_t i1) {
    std::vector<T> buffers(7 * w);
    T* __restrict__ edge = buffers.data();
    T* __restrict__ low = edge + w;
    T* __restrict__ gap = low + w;
    T* __restrict__ l_var = gap + w;
    T* __restrict__ l_dist = l_var + w;
    T* __restrict__ l_edge = l_dist + w;
    T* __restrict__ l_gap = l_edge + w;
    for (int64_t i = i0; i < i1; ++i) {
      column_window<T, true>(hi, edge, i, h, w, edge_r);
      column_window<T, false>(lo, low, i, h, w, edge_r);
      column_window<T, true>(hb, gap, i, h, w, lidar_r);
      const T* __restrict__ zi = z + i * w;
      const T* __restrict__ di = d + i * w;
      const T* __restrict__ ri = wh + i * (w - 1);
      const T* __restrict__ down = i + 1 < h ? wv + i * w : nullptr;
      const T* __restrict__ up = i > 0 ? wv + (i - 1) * w : nullptr;
      const T* __restrict__ disti = dist + i * w;
      T* __restrict__ f_z = features + i * w;
      T* __restrict__ f_var = f_z + n;
      T* __restrict__ f_dist = f_var + n;
      T* __restrict__ f_edge = f_dist + n;
      T* __restrict__ f_gap = f_edge + n;
      // A_ii in the order grid_conditional_variance adds it: d, the right, left, lower and upper weights.
      std::copy(di, di + w, f_var);
#pragma omp simd
      for (int64_t j = 0; j < w - 1; ++j) f_var[j] += ri[j];
#pragma omp simd
      for (int64_t j = 1; j < w; ++j) f_var[j] += ri[j - 1];
      if (down) {
#pragma omp simd
        for (int64_t j = 0; j < w; ++j) f_var[j] += down[j];
      }
      if (up) {
#pragma omp simd
        for (int64_t j = 0; j < w; ++j) f_var[j] += up[j];
      }
      // (std_in_metres(sqrt(1 / A_ii)) / z)^2: the conditional variance in (log z)^2
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) {
        const T s = std::sqrt(T(1) / f_var[j]);
        const T sm = power == 0 ? s : (power == 1 ? s * zi[j] : s * (zi[j] * zi[j]));
        const T v = sm / zi[j];
        f_var[j] = v * v;
      }
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) {
        f_z[j] = zi[j];
        f_dist[j] = disti[j];
        f_edge[j] = edge[j] + (-low[j]);  // window_max(log x) + window_max(-log x)
        f_gap[j] = gap[j];
        l_var[j] = std::max(f_var[j] + T(1e-6), T(1e-12));
        l_dist[j] = std::max(disti[j] + T(1), T(1e-12));
        l_edge[j] = std::max(f_edge[j] + T(0.01), T(1e-12));
        l_gap[j] = std::max(gap[j] + T(0.01), T(1e-12));
      }
      log_inplace(l_var, w);
      log_inplace(l_dist, w);
      log_inplace(l_edge, w);
      log_inplace(l_gap, w);
      const T* __restrict__ li = lx + i * w;
      T* __restrict__ out = std_out + i * w;
#pragma omp simd
      for (int64_t j = 0; j < w; ++j)  // log z: pass 1's log(max(z, 1e-3)), the same number where z >= 1e-3
        out[j] = c0 + ((((c1 * li[j] + c2 * l_var[j]) + c3 * l_dist[j]) + c4 * l_edge[j]) + c5 * l_gap[j]);
      for (int64_t j = 0; j < w; ++j) {
        if (zi[j] < T(1e-3)) {
          const T lz = std::log(std::max(zi[j], T(1e-12)));
          out[j] = c0 + ((((c1 * lz + c2 * l_var[j]) + c3 * l_dist[j]) + c4 * l_edge[j]) + c5 * l_gap[j]);
        }
      }
      exp_inplace(out, w);
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) out[j] = std::sqrt(out[j] * out[j] + noise2);
    }
  });
}

// The predictive std and its five signals of (B, 1, H, W) depth, LiDAR depth, gate (an empty tensor:
// none), distance to the nearest kept return, and the last system's diagonal d (B, H, W) and weights
// wh (B, H, W-1), wv (B, H-1, W) in the unknown's units (power: 0 depth, 1 log, 2 inverse depth).
std::vector<torch::Tensor> predictive_std(torch::Tensor z, torch::Tensor sparse, torch::Tensor gate,
                                          torch::Tensor dist, torch::Tensor d, torch::Tensor wh, torch::Tensor wv,
                                          int64_t power, std::vector<double> weights, double noise, int64_t edge_window,
                                          int64_t lidar_window) {
  TORCH_CHECK(weights.size() == 6, "predictive_std: expected 6 weights");
  for (const auto* t : {&z, &sparse, &dist, &d, &wh, &wv})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == z.scalar_type(),
                "predictive_std: expected contiguous CPU tensors of one dtype");
  const bool gated = gate.numel() > 0;
  TORCH_CHECK(!gated || (gate.is_contiguous() && gate.scalar_type() == z.scalar_type()), "predictive_std: gate");
  const int64_t b = z.size(0), h = z.size(2), w = z.size(3), n = h * w;
  auto std_out = torch::empty_like(z);
  auto features = torch::empty({b, 5, h, w}, z.options());
  auto scratch = crfdepth_workspace::scratch(crfdepth_workspace::kPredictiveStd, 4 * n, z.scalar_type());
  AT_DISPATCH_FLOATING_TYPES(z.scalar_type(), "predictive_std", [&] {
    scalar_t* s[4];
    for (int k = 0; k < 4; ++k) s[k] = scratch.data_ptr<scalar_t>() + k * n;
    for (int64_t k = 0; k < b; ++k) {
      std_frame<scalar_t>(z.data_ptr<scalar_t>() + k * n, sparse.data_ptr<scalar_t>() + k * n,
                          gated ? gate.data_ptr<scalar_t>() + k * n : nullptr, dist.data_ptr<scalar_t>() + k * n,
                          d.data_ptr<scalar_t>() + k * n, wh.data_ptr<scalar_t>() + k * h * (w - 1),
                          wv.data_ptr<scalar_t>() + k * (h - 1) * w, static_cast<int>(power), weights.data(), noise,
                          edge_window / 2, lidar_window / 2, h, w, std_out.data_ptr<scalar_t>() + k * n,
                          features.data_ptr<scalar_t>() + k * 5 * n, s[0], s[1], s[2], s[3]);
    }
  });
  return {std_out, features};
}

}  // namespace

void register_std(pybind11::module& m) {
  m.def("predictive_std", &predictive_std, "the predictive std and its signals of pixel-grid frames");
}

}  // namespace crfdepth_predictive_std
