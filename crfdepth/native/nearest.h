// The exact nearest valid pixel of every pixel (Euclidean), in linear time (docs/design.md section 4b):
// what crfdepth/geometry/nearest.py computes with torch and crfdepth/fill/nearest.py with SciPy.
//
// A pass down each column finds the nearest valid row; along each row the lower envelope of the
// parabolas (x - q)^2 + g(q)^2 then gives the nearest valid pixel (Felzenszwalb and Huttenlocher
// 2012). Ties go to the lowest row, then the lowest column, as SciPy's distance_transform_edt.
// Distances are kept in 32-bit integers where (H + W)^2 fits (any frame up to 46,000 pixels a
// side), which halves the memory these passes touch.

#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace crfdepth_nearest {

namespace {

constexpr int64_t kColumns = 256;  // columns per task of the column pass
constexpr int64_t kRowsPerTask = 16;

// One (H, W) frame: ``marks`` > 0 are the valid pixels. For every pixel, out(flat, source, squared) is
// called once with the flat index of its nearest valid pixel (-1 in a frame without one) and the
// squared distance to it (``big`` where none). ``g2`` and ``src`` are (H, W) scratch.
template <typename I, typename V, typename Out>
void nearest_frame(const V* marks, int64_t h, int64_t w, I big, I* g2, I* src, Out out) {
  // Column pass: the nearest valid row above (src), then below, and the squared distance (g2).
  at::parallel_for(0, w, kColumns, [=](int64_t c0, int64_t c1) {
    std::vector<I> last(c1 - c0, I(-1));
    I* __restrict__ lv = last.data();
    for (int64_t r = 0; r < h; ++r) {
      const V* __restrict__ vr = marks + r * w + c0;
      I* __restrict__ sr = src + r * w + c0;
#pragma omp simd
      for (int64_t c = 0; c < c1 - c0; ++c) {
        lv[c] = vr[c] > 0 ? I(r) : lv[c];
        sr[c] = lv[c];
      }
    }
    std::fill(last.begin(), last.end(), I(-1));
    for (int64_t r = h - 1; r >= 0; --r) {
      const V* __restrict__ vr = marks + r * w + c0;
      I* __restrict__ sr = src + r * w + c0;
      I* __restrict__ gr = g2 + r * w + c0;
      const I ri = I(r);
#pragma omp simd
      for (int64_t c = 0; c < c1 - c0; ++c) {
        lv[c] = vr[c] > 0 ? ri : lv[c];
        const I above = sr[c], below = lv[c];
        const I du = above >= 0 ? (ri - above) * (ri - above) : big;
        const I dd = below >= 0 ? (below - ri) * (below - ri) : big;
        const bool take_up = du <= dd;  // ties: the row above
        sr[c] = take_up ? above : below;
        gr[c] = take_up ? du : dd;
      }
    }
  });
  // Row pass: the lower envelope of the parabolas q -> (x - q)^2 + g2(q) over the columns q with g2 < big.
  // The boundary where parabola q takes over from p lies at s = num / den with num = f(q) - f(p),
  // f(q) = g2(q) + q^2, and den = 2 (q - p) > 0: kept as that fraction and compared by cross
  // multiplication, exactly and without a division (products stay below 2^63 for any frame here).
  at::parallel_for(0, h, kRowsPerTask, [&](int64_t r0, int64_t r1) {
    std::vector<int64_t> site(w), fval(w), gval(w), num(w + 1), den(w + 1);
    for (int64_t r = r0; r < r1; ++r) {
      const I* __restrict__ g = g2 + r * w;
      const I* __restrict__ rs = src + r * w;
      int64_t k = -1;
      for (int64_t q = 0; q < w; ++q) {
        if (g[q] >= big) continue;
        const int64_t fq = static_cast<int64_t>(g[q]) + q * q;
        int64_t sn = 0, sd = 1;
        while (k >= 0) {
          sn = fq - fval[k];
          sd = 2 * (q - site[k]);
          if (k > 0 && sn * den[k] <= num[k] * sd) --k; else break;  // s <= boundary k: parabola k is hidden
        }
        ++k;
        site[k] = q;
        fval[k] = fq;
        gval[k] = g[q];
        num[k] = sn;
        den[k] = sd;
      }
      const int64_t row = r * w;
      if (k < 0) {  // no valid pixel in the frame reaches this row (the frame has none)
        for (int64_t x = 0; x < w; ++x) out(row + x, int64_t(-1), static_cast<int64_t>(big));
        continue;
      }
      int64_t j = 0;
      for (int64_t x = 0; x < w; ++x) {
        while (j < k && num[j + 1] < x * den[j + 1]) ++j;  // boundary j + 1 lies left of x
        const int64_t col = site[j], dx = x - col;
        out(row + x, static_cast<int64_t>(rs[col]) * w + col, dx * dx + gval[j]);
      }
    }
  });
}

// Every frame of (B, H, W) ``marks`` (out gets the frame's first flat index as well), with 32-bit scratch where (H + W)^2 fits, else 64-bit.
template <typename V, typename Out>
void nearest_frames(const V* marks, int64_t b, int64_t h, int64_t w, Out out) {
  const int64_t big = (h + w) * (h + w) + 1;
  const bool narrow = big < std::numeric_limits<int32_t>::max();
  auto scratch = torch::empty({2, h, w}, torch::dtype(narrow ? torch::kInt32 : torch::kInt64));
  for (int64_t f = 0; f < b; ++f) {
    const int64_t base = f * h * w;
    auto frame_out = [&out, base](int64_t flat, int64_t source, int64_t squared) {
      out(base, flat, source, squared);
    };
    if (narrow) {
      int32_t* s = scratch.data_ptr<int32_t>();
      nearest_frame<int32_t>(marks + f * h * w, h, w, static_cast<int32_t>(big), s, s + h * w, frame_out);
    } else {
      int64_t* s = scratch.data_ptr<int64_t>();
      nearest_frame<int64_t>(marks + f * h * w, h, w, big, s, s + h * w, frame_out);
    }
  }
}

// (B, H, W) bool -> the flat index row * W + col of each pixel's nearest valid pixel (-1 in a frame
// without one) and the squared distance ((H + W)^2 + 1 there), both int64.
std::vector<torch::Tensor> nearest_valid(torch::Tensor valid) {
  TORCH_CHECK(valid.device().is_cpu() && valid.is_contiguous() && valid.scalar_type() == torch::kBool,
              "nearest_valid: expected a contiguous CPU bool tensor");
  const int64_t b = valid.size(0), h = valid.size(1), w = valid.size(2);
  auto index = torch::empty({b, h, w}, valid.options().dtype(torch::kInt64));
  auto squared = torch::empty({b, h, w}, valid.options().dtype(torch::kInt64));
  int64_t* idx = index.data_ptr<int64_t>();
  int64_t* sq = squared.data_ptr<int64_t>();
  nearest_frames(valid.data_ptr<bool>(), b, h, w, [=](int64_t base, int64_t e, int64_t source, int64_t d2) {
    idx[base + e] = source;
    sq[base + e] = d2;
  });
  return {index, squared};
}

// (B, H, W) depth, 0 = none -> the depth of each pixel's nearest return (0 in a frame without one) and
// the Euclidean distance to it in pixels (the image diagonal in a frame without one), in the depth's
// dtype: the nearest fill and the predictive std's distance signal in one search.
std::vector<torch::Tensor> nearest_fill(torch::Tensor depth) {
  TORCH_CHECK(depth.device().is_cpu() && depth.is_contiguous() && depth.dim() == 3,
              "nearest_fill: expected a contiguous CPU (B, H, W) tensor");
  const int64_t b = depth.size(0), h = depth.size(1), w = depth.size(2);
  auto filled = torch::empty_like(depth);
  auto distance = torch::empty_like(depth);
  AT_DISPATCH_FLOATING_TYPES(depth.scalar_type(), "nearest_fill", [&] {
    const scalar_t* d = depth.data_ptr<scalar_t>();
    scalar_t* fo = filled.data_ptr<scalar_t>();
    scalar_t* dist = distance.data_ptr<scalar_t>();
    const scalar_t diagonal = static_cast<scalar_t>(std::hypot(static_cast<double>(h), static_cast<double>(w)));
    nearest_frames(d, b, h, w, [=](int64_t base, int64_t e, int64_t source, int64_t d2) {
      if (source < 0) {
        fo[base + e] = scalar_t(0);
        dist[base + e] = diagonal;
        return;
      }
      fo[base + e] = d[base + source];
      dist[base + e] = static_cast<scalar_t>(std::sqrt(static_cast<double>(d2)));
    });
  });
  return {filled, distance};
}

}  // namespace

void register_nearest(pybind11::module& m) {
  m.def("nearest_valid", &nearest_valid, "exact nearest valid pixel and squared distance");
  m.def("nearest_fill", &nearest_fill, "nearest return's depth and the distance to it, exactly");
}

}  // namespace crfdepth_nearest
