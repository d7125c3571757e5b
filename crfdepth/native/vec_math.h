// Element-wise logarithm and exponential of a row, in place, with torch's own vectorised functions
// (at::vec::Vectorized: SLEEF's where the build has AVX2, the standard library's otherwise).

#pragma once

#include <ATen/cpu/vec/vec.h>

#include <cstdint>

namespace crfdepth_vec {

template <typename T>
void log_inplace(T* x, int64_t n) {
  using Vec = at::vec::Vectorized<T>;
  int64_t j = 0;
  for (; j + Vec::size() <= n; j += Vec::size()) Vec::loadu(x + j).log().store(x + j);
  if (j < n) Vec::loadu(x + j, n - j).log().store(x + j, n - j);
}

template <typename T>
void exp_inplace(T* x, int64_t n) {
  using Vec = at::vec::Vectorized<T>;
  int64_t j = 0;
  for (; j + Vec::size() <= n; j += Vec::size()) Vec::loadu(x + j).exp().store(x + j);
  if (j < n) Vec::loadu(x + j, n - j).exp().store(x + j, n - j);
}

}  // namespace crfdepth_vec
