#include "torch/width_counts.h"

#include <atomic>

namespace dyq {
namespace {

// Relaxed atomics: each count is exact, and a reader needs no order between different widths.
std::array<std::atomic<int64_t>, kNumActivationWidths> counts{};

}  // namespace

void count_gemm_call(int64_t act_bits) {
  const int index = act_bits_index(act_bits);
  if (index >= 0) counts[index].fetch_add(1, std::memory_order_relaxed);
}

std::array<int64_t, kNumActivationWidths> gemm_width_counts() {
  std::array<int64_t, kNumActivationWidths> snapshot{};
  for (int i = 0; i < kNumActivationWidths; ++i) snapshot[i] = counts[i].load(std::memory_order_relaxed);
  return snapshot;
}

void reset_gemm_width_counts() {
  for (auto& count : counts) count.store(0, std::memory_order_relaxed);
}

}  // namespace dyq
