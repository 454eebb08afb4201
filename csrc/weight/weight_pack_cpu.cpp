// INT4 weight quantization (docs/numerics.md, section 1).
#include "weight/weight_pack_cpu.h"

#include <atomic>
#include <cmath>

#include "common/format.h"
#include "parallel/parallel.h"

namespace dyq::cpu {
namespace {
constexpr int64_t kRowGrain = 16;
}

bool quantize_weight(const float* weight, int64_t n, int64_t k, int group_size, uint8_t* qweight, float* scales) {
  const int64_t groups = group_count(k, group_size);
  std::atomic<bool> finite{true};
  parallel_for(0, n, kRowGrain, [&](int64_t row_begin, int64_t row_end) {
    for (int64_t row = row_begin; row < row_end; ++row) {
      for (int64_t g = 0; g < groups; ++g) {
        const int64_t columns = group_columns(k, group_size, g);  // even: k is
        const float* w = weight + row * k + g * group_size;
        float absmax = 0.0f;
        for (int64_t i = 0; i < columns; ++i) {
          if (!std::isfinite(w[i])) {
            finite.store(false, std::memory_order_relaxed);
            return;
          }
          absmax = std::fmax(absmax, std::fabs(w[i]));
        }
        const float scale = weight_scale_from_absmax(absmax);
        uint8_t* packed = qweight + (row * k + g * group_size) / 2;
        if (scale == 0.0f) {
          scales[row * groups + g] = 1.0f;
          for (int64_t i = 0; i < columns / 2; ++i) packed[i] = 0;
          continue;
        }
        scales[row * groups + g] = scale;
        for (int64_t i = 0; i < columns / 2; ++i) {
          packed[i] = pack_weight_pair(weight_code(w[2 * i], scale), weight_code(w[2 * i + 1], scale));
        }
      }
    }
  });
  return finite.load();
}

void dequantize_weight(const uint8_t* qweight, const float* scales, int64_t n, int64_t k, int group_size,
                       float* out) {
  const int64_t groups = group_count(k, group_size);
  parallel_for(0, n, kRowGrain, [&](int64_t row_begin, int64_t row_end) {
    for (int64_t row = row_begin; row < row_end; ++row) {
      for (int64_t col = 0; col < k; col += 2) {
        const uint8_t byte = qweight[(row * k + col) / 2];
        const float scale = scales[row * groups + col / group_size];
        out[row * k + col] = scale * static_cast<float>(sign_extend_nibble(byte & 0xFu));
        out[row * k + col + 1] = scale * static_cast<float>(sign_extend_nibble(byte >> 4));
      }
    }
  });
}

}  // namespace dyq::cpu
