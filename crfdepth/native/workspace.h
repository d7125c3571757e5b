// Scratch memory kept between calls. A fresh block of several megabytes costs the operating system's
// page faults at every call (about 1 ms for 8 MB here, a tenth of a frame's solve); the kernels'
// callers hold Python's GIL, so one call at a time uses a slot. Blocks over kKeepBytes are not kept.

#pragma once

#include <torch/extension.h>

#include <cstdint>

namespace crfdepth_workspace {

constexpr int64_t kKeepBytes = int64_t(64) << 20;

enum Slot { kGridSolve = 0, kPredictiveStd = 1, kSlots = 2 };

// At least `numel` elements of `dtype`, the same block as the previous call's where it is large enough.
inline torch::Tensor scratch(Slot slot, int64_t numel, c10::ScalarType dtype) {
  static torch::Tensor blocks[kSlots];
  torch::Tensor& kept = blocks[slot];
  if (kept.defined() && kept.scalar_type() == dtype && kept.numel() >= numel) return kept;
  auto block = torch::empty({numel}, torch::dtype(dtype));
  if (numel * static_cast<int64_t>(c10::elementSize(dtype)) <= kKeepBytes) kept = block;
  return block;
}

}  // namespace crfdepth_workspace
