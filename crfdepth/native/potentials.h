// The pixel grid's affinities in fused passes (docs/design.md sections 3 and 4b): what
// crfdepth/potentials/energy.py's grid_potentials computes with torch when no gradient is needed
// (colour_affinity, normal_affinity of dense_normals, distance_affinity of camera_points), with
// the same formulas and the same order of operations, for each 4-neighbour edge of each frame; each
// row's exponents go through torch's vectorised exp while they are in cache.

#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <cstdint>
#include <vector>

#include "vec_math.h"

namespace crfdepth_potentials {

namespace {

constexpr int64_t kRows = 8;  // rows per task at least

// Back-projected points p = z (ray_x, ray_y, 1) of one H x W frame, as planes px, py (pz is the depth).
template <typename T>
void camera_points(const T* z, T fx, T fy, T cx, T cy, T skew, T* px, T* py, int64_t h, int64_t w) {
  at::parallel_for(0, h, kRows, [=](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const T ray_y = (static_cast<T>(i) - cy) / fy;
      const T* __restrict__ zi = z + i * w;
      T* __restrict__ xi = px + i * w;
      T* __restrict__ yi = py + i * w;
#pragma omp simd
      for (int64_t j = 0; j < w; ++j) {
        const T ray_x = ((static_cast<T>(j) - cx) - skew * ray_y) / fx;
        xi[j] = zi[j] * ray_x;
        yi[j] = zi[j] * ray_y;
      }
    }
  });
}

// The edge-aware normals of dense_normals: per axis the one-sided difference (forward or backward)
// with the smaller depth change (ties forward; at a border the only side there is), their cross
// product, facing the camera, zero where the pixel or one of its 4 neighbours has no depth.
template <typename T>
void dense_normals(const T* px, const T* py, const T* pz, T* nx, T* ny, T* nz, int64_t h, int64_t w) {
  // the normal from the two differences p[a1] - p[a0] (along the row) and p[b1] - p[b0] (down the column)
  auto normal = [=](int64_t e, int64_t a0, int64_t a1, int64_t b0, int64_t b1, bool valid) {
    const T ax = px[a1] - px[a0], ay = py[a1] - py[a0], az = pz[a1] - pz[a0];
    const T bx = px[b1] - px[b0], by = py[b1] - py[b0], bz = pz[b1] - pz[b0];
    const T cx = ay * bz - az * by, cy = az * bx - ax * bz, cz = ax * by - ay * bx;
    const T length = std::max(std::sqrt(cx * cx + cy * cy + cz * cz), static_cast<T>(1e-12));
    const T facing = cx * px[e] + cy * py[e] + cz * pz[e];
    const T scale = (facing > 0 ? T(-1) : T(1)) * (valid ? T(1) : T(0)) / length;
    nx[e] = cx * scale;
    ny[e] = cy * scale;
    nz[e] = cz * scale;
  };
  // a pixel on the border: the only side there is, and neighbours outside the image count as present
  auto border = [=](int64_t i, int64_t j) {
    const int64_t e = i * w + j;
    int64_t a0, a1, b0, b1;
    if (w == 2 || j == 0) {
      a0 = i * w; a1 = a0 + 1;
    } else if (j == w - 1) {
      a0 = e - 1; a1 = e;
    } else if (std::abs(pz[e + 1] - pz[e]) <= std::abs(pz[e] - pz[e - 1])) {  // ties forward
      a0 = e; a1 = e + 1;
    } else {
      a0 = e - 1; a1 = e;
    }
    if (h == 2 || i == 0) {
      b0 = j; b1 = w + j;
    } else if (i == h - 1) {
      b0 = e - w; b1 = e;
    } else if (std::abs(pz[e + w] - pz[e]) <= std::abs(pz[e] - pz[e - w])) {
      b0 = e; b1 = e + w;
    } else {
      b0 = e - w; b1 = e;
    }
    const bool valid = pz[e] > 0 && (j == 0 || pz[e - 1] > 0) && (j == w - 1 || pz[e + 1] > 0) &&
                       (i == 0 || pz[e - w] > 0) && (i == h - 1 || pz[e + w] > 0);
    normal(e, a0, a1, b0, b1, valid);
  };
  at::parallel_for(0, h, kRows, [=](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      if (i == 0 || i == h - 1 || w <= 2) {
        for (int64_t j = 0; j < w; ++j) border(i, j);
        continue;
      }
      border(i, 0);
      border(i, w - 1);
      const T* __restrict__ x = px + i * w;
      const T* __restrict__ y = py + i * w;
      const T* __restrict__ z = pz + i * w;
      const T* __restrict__ xu = x - w;
      const T* __restrict__ yu = y - w;
      const T* __restrict__ zu = z - w;
      const T* __restrict__ xd = x + w;
      const T* __restrict__ yd = y + w;
      const T* __restrict__ zd = z + w;
      T* __restrict__ ox = nx + i * w;
      T* __restrict__ oy = ny + i * w;
      T* __restrict__ oz = nz + i * w;
      // inside the frame, branch-free: both sides computed, the one with the smaller depth change taken
#pragma omp simd
      for (int64_t j = 1; j < w - 1; ++j) {
        // selects of values computed on both sides (no branch: the loop vectorises)
        const T fx = x[j + 1] - x[j], fy = y[j + 1] - y[j], fz = z[j + 1] - z[j];
        const T gx = x[j] - x[j - 1], gy = y[j] - y[j - 1], gz = z[j] - z[j - 1];
        const bool row_fwd = std::abs(fz) <= std::abs(gz);
        const T ax = row_fwd ? fx : gx, ay = row_fwd ? fy : gy, az = row_fwd ? fz : gz;
        const T dx = xd[j] - x[j], dy = yd[j] - y[j], dz = zd[j] - z[j];
        const T ux = x[j] - xu[j], uy = y[j] - yu[j], uz = z[j] - zu[j];
        const bool col_fwd = std::abs(dz) <= std::abs(uz);
        const T bx = col_fwd ? dx : ux, by = col_fwd ? dy : uy, bz = col_fwd ? dz : uz;
        const T cx = ay * bz - az * by, cy = az * bx - ax * bz, cz = ax * by - ay * bx;
        const T length = std::max(std::sqrt(cx * cx + cy * cy + cz * cz), static_cast<T>(1e-12));
        const T facing = cx * x[j] + cy * y[j] + cz * z[j];
        const bool valid = (z[j] > 0) & (z[j - 1] > 0) & (z[j + 1] > 0) & (zu[j] > 0) & (zd[j] > 0);
        const T scale = (facing > 0 ? T(-1) : T(1)) * (valid ? T(1) : T(0)) / length;
        ox[j] = cx * scale;
        oy[j] = cy * scale;
        oz[j] = cz * scale;
      }
    }
  });
}

// -sum_c (a_c - b_c)^2 / sigma^2 (then its exp: the affinity) over the edges to the right (out_h) and downwards (out_v) of
// three planes at stride `plane`.
template <typename T>
void squared_distance_affinity(const T* v, int64_t plane, T sigma2, T* out_h, T* out_v, int64_t h, int64_t w) {
  at::parallel_for(0, h, kRows, [=](int64_t i0, int64_t i1) {
    const T* __restrict__ v0 = v;
    const T* __restrict__ v1 = v + plane;
    const T* __restrict__ v2 = v + 2 * plane;
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t r = i * w;
      T* __restrict__ oh = out_h + i * (w - 1);
#pragma omp simd
      for (int64_t j = 0; j < w - 1; ++j) {
        const T d0 = v0[r + j] - v0[r + j + 1], d1 = v1[r + j] - v1[r + j + 1], d2 = v2[r + j] - v2[r + j + 1];
        oh[j] = -(d0 * d0 + d1 * d1 + d2 * d2) / sigma2;
      }
      crfdepth_vec::exp_inplace(oh, w - 1);
      if (i + 1 < h) {
        T* __restrict__ ov = out_v + i * w;
#pragma omp simd
        for (int64_t j = 0; j < w; ++j) {
          const T d0 = v0[r + j] - v0[r + w + j], d1 = v1[r + j] - v1[r + w + j], d2 = v2[r + j] - v2[r + w + j];
          ov[j] = -(d0 * d0 + d1 * d1 + d2 * d2) / sigma2;
        }
        crfdepth_vec::exp_inplace(ov, w);
      }
    }
  });
}

// exp((clamp(n_i . n_j, -1, 1) - 1) / sigma^2), the affinity, over the edges, of three planes at stride `plane`.
template <typename T>
void cosine_affinity(const T* n, int64_t plane, T sigma2, T* out_h, T* out_v, int64_t h, int64_t w) {
  at::parallel_for(0, h, kRows, [=](int64_t i0, int64_t i1) {
    const T* __restrict__ n0 = n;
    const T* __restrict__ n1 = n + plane;
    const T* __restrict__ n2 = n + 2 * plane;
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t r = i * w;
      T* __restrict__ oh = out_h + i * (w - 1);
#pragma omp simd
      for (int64_t j = 0; j < w - 1; ++j) {
        const T c = n0[r + j] * n0[r + j + 1] + n1[r + j] * n1[r + j + 1] + n2[r + j] * n2[r + j + 1];
        oh[j] = (std::min(std::max(c, T(-1)), T(1)) - T(1)) / sigma2;
      }
      crfdepth_vec::exp_inplace(oh, w - 1);
      if (i + 1 < h) {
        T* __restrict__ ov = out_v + i * w;
#pragma omp simd
        for (int64_t j = 0; j < w; ++j) {
          const T c = n0[r + j] * n0[r + w + j] + n1[r + j] * n1[r + w + j] + n2[r + j] * n2[r + w + j];
          ov[j] = (std::min(std::max(c, T(-1)), T(1)) - T(1)) / sigma2;
        }
        crfdepth_vec::exp_inplace(ov, w);
      }
    }
  });
}

template <typename T>
void affinities_one(const T* image, const T* depth, const T* k, T sd2, T sn2, T sp2, bool colour, bool normal,
                    bool distance, T* ch, T* cv, T* nh, T* nv, T* dh, T* dv, T* work, int64_t h, int64_t w) {
  const int64_t plane = h * w;
  if (colour) squared_distance_affinity<T>(image, plane, sd2, ch, cv, h, w);
  if (!normal && !distance) return;
  T* points = work;  // x, y planes then the depth copied as z: three planes at stride `plane`
  camera_points<T>(depth, k[0], k[4], k[2], k[5], k[1], points, points + plane, h, w);
  std::copy(depth, depth + plane, points + 2 * plane);
  if (normal) {
    T* normals = work + 3 * plane;
    dense_normals<T>(points, points + plane, points + 2 * plane, normals, normals + plane, normals + 2 * plane, h, w);
    cosine_affinity<T>(normals, plane, sn2, nh, nv, h, w);
  }
  if (distance) squared_distance_affinity<T>(points, plane, sp2, dh, dv, h, w);
}

}  // namespace

// image (B, 3, H, W), depth (B, H, W) (ignored unless normal or distance), K (B, 3, 3), the sigmas
// squared; H, W >= 2. Returns the affinities [colour_h, colour_v, normal_h, normal_v, distance_h,
// distance_v], (B, H, W-1) and (B, H-1, W) maps; the pairs not asked for are empty.
std::vector<torch::Tensor> grid_affinities(torch::Tensor image, torch::Tensor depth, torch::Tensor K, double sd2,
                                           double sn2, double sp2, bool colour, bool normal, bool distance) {
  TORCH_CHECK(image.device().is_cpu() && image.is_contiguous() && depth.is_contiguous(),
              "grid_affinities: expected contiguous CPU tensors");
  const int64_t b = image.size(0), h = image.size(2), w = image.size(3);
  TORCH_CHECK(h >= 2 && w >= 2, "grid_affinities: expected H, W >= 2");
  auto opts = image.options();
  auto pair = [&](bool on) {
    return on ? std::vector<torch::Tensor>{torch::empty({b, h, w - 1}, opts), torch::empty({b, h - 1, w}, opts)}
              : std::vector<torch::Tensor>{torch::empty({0}, opts), torch::empty({0}, opts)};
  };
  auto c = pair(colour), nn = pair(normal), d = pair(distance);
  auto work = torch::empty({(normal || distance) ? 6 * h * w : 0}, opts);
  auto k = K.to(image.scalar_type()).contiguous();
  AT_DISPATCH_FLOATING_TYPES(image.scalar_type(), "grid_affinities", [&] {
    using T = scalar_t;
    auto at = [](torch::Tensor& t, bool on, int64_t offset) { return on ? t.data_ptr<T>() + offset : nullptr; };
    for (int64_t f = 0; f < b; ++f) {
      const int64_t eh = f * h * (w - 1), ev = f * (h - 1) * w;
      affinities_one<T>(image.data_ptr<T>() + f * 3 * h * w, (normal || distance) ? depth.data_ptr<T>() + f * h * w : nullptr,
                        k.data_ptr<T>() + 9 * f, static_cast<T>(sd2), static_cast<T>(sn2), static_cast<T>(sp2), colour,
                        normal, distance, at(c[0], colour, eh), at(c[1], colour, ev), at(nn[0], normal, eh),
                        at(nn[1], normal, ev), at(d[0], distance, eh), at(d[1], distance, ev), work.data_ptr<T>(), h, w);
    }
  });
  return {c[0], c[1], nn[0], nn[1], d[0], d[1]};
}

// The grid system's maps, element by element in the order crfdepth/potentials/energy.py's grid_system
// takes them: out = ((beta c + gamma n) + delta p) f, with the terms that are off left out.
template <typename T>
__attribute__((noinline)) void edge_weights(const T* __restrict__ c, const T* __restrict__ n, const T* __restrict__ p,
                                            const T* __restrict__ f, T beta, T gamma, T delta, T* __restrict__ out,
                                            int64_t lo, int64_t hi) {
#pragma omp simd
  for (int64_t k = lo; k < hi; ++k) {
    T v = beta * c[k];
    if (n) v = v + gamma * n[k];
    if (p) v = v + delta * p[k];
    if (f) v = v * f[k];
    out[k] = v;
  }
}

// d = alpha w + eps and b = (alpha w) z + eps prior: unary_system of (alpha w, z) and (eps, prior).
template <typename T>
__attribute__((noinline)) void unary_maps(const T* __restrict__ w, const T* __restrict__ z, const T* __restrict__ x0,
                                          T alpha, T eps, T* __restrict__ d, T* __restrict__ b, int64_t lo, int64_t hi) {
#pragma omp simd
  for (int64_t k = lo; k < hi; ++k) {
    const T u = alpha * w[k];
    d[k] = u + eps;
    b[k] = u * z[k] + eps * x0[k];
  }
}

// (d, b, wh, wv) of a round's maps (B, H, W) w, z, prior and edge pairs (B, H, W-1) / (B, H-1, W): colour, and
// normal, distance and the head's factor where given (empty tensors where off), with their scalar weights.
std::vector<torch::Tensor> grid_system(torch::Tensor w, torch::Tensor z, torch::Tensor prior, torch::Tensor ch,
                                       torch::Tensor cv, torch::Tensor nh, torch::Tensor nv, torch::Tensor dh,
                                       torch::Tensor dv, torch::Tensor fh, torch::Tensor fv, double alpha, double beta,
                                       double gamma, double delta, double eps) {
  for (const auto* t : {&w, &z, &prior, &ch, &cv, &nh, &nv, &dh, &dv, &fh, &fv})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && (t->numel() == 0 || t->scalar_type() == w.scalar_type()),
                "grid_system: expected contiguous CPU tensors of one dtype");
  auto d = torch::empty_like(w), b = torch::empty_like(w), wh = torch::empty_like(ch), wv = torch::empty_like(cv);
  AT_DISPATCH_FLOATING_TYPES(w.scalar_type(), "grid_system", [&] {
    using T = scalar_t;
    auto ptr = [](torch::Tensor& t) -> const T* { return t.numel() ? t.data_ptr<T>() : nullptr; };
    const T *pw = ptr(w), *pz = ptr(z), *px = ptr(prior);
    const T *pch = ptr(ch), *pcv = ptr(cv), *pnh = ptr(nh), *pnv = ptr(nv), *pdh = ptr(dh), *pdv = ptr(dv);
    const T *pfh = ptr(fh), *pfv = ptr(fv);
    T *pd = d.data_ptr<T>(), *pb = b.data_ptr<T>(), *pwh = wh.data_ptr<T>(), *pwv = wv.data_ptr<T>();
    const T a = T(alpha), be = T(beta), g = T(gamma), de = T(delta), e = T(eps);
    const int64_t n = w.numel(), nhz = ch.numel(), nvt = cv.numel();
    at::parallel_for(0, n, 32768, [=](int64_t lo, int64_t hi) { unary_maps<T>(pw, pz, px, a, e, pd, pb, lo, hi); });
    at::parallel_for(0, nhz, 32768, [=](int64_t lo, int64_t hi) {
      edge_weights<T>(pch, pnh, pdh, pfh, be, g, de, pwh, lo, hi);
    });
    at::parallel_for(0, nvt, 32768, [=](int64_t lo, int64_t hi) {
      edge_weights<T>(pcv, pnv, pdv, pfv, be, g, de, pwv, lo, hi);
    });
  });
  return {d, b, wh, wv};
}

void register_potentials(pybind11::module& m) {
  m.def("grid_affinities", &grid_affinities, "colour, normal and 3D-distance affinities of a pixel grid's edges");
  m.def("grid_system", &grid_system, "the pixel grid system's diagonal, right-hand side and edge weights");
}

}  // namespace crfdepth_potentials
