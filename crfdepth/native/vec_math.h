// Element-wise logarithm and exponential of a row, in place, with torch's own vectorised functions
// (at::vec::Vectorized: SLEEF's where the build has AVX2, the standard library's otherwise).

#pragma once

#include <ATen/cpu/vec/vec.h>

#include <cstdint>

namespace crfdepth_vec {

// x[j] <- f(x[j]) for j < n, f taking and returning an at::vec::Vectorized<T>.
template <typename T, typename F>
void map_inplace(T* x, int64_t n, F f) {
  using Vec = at::vec::Vectorized<T>;
  int64_t j = 0;
  for (; j + Vec::size() <= n; j += Vec::size()) f(Vec::loadu(x + j)).store(x + j);
  if (j < n) f(Vec::loadu(x + j, n - j)).store(x + j, n - j);
}

template <typename T>
void log_inplace(T* x, int64_t n) {
  map_inplace(x, n, [](const at::vec::Vectorized<T>& v) { return v.log(); });
}

template <typename T>
void exp_inplace(T* x, int64_t n) {
  map_inplace(x, n, [](const at::vec::Vectorized<T>& v) { return v.exp(); });
}

}  // namespace crfdepth_vec
