// Quantization of one activation row (docs/numerics.md, section 2), shared by the standalone
// quantizer and the GEMM that fuses it.
#pragma once

#include <cmath>
#include <cstdint>

#include "common/cpu_dtype.h"
#include "common/format.h"

namespace dyq::cpu {

// Quantizes the k values of `x` group by group. For each group calls
// on_group(group_index, params, codes) where codes[0..group_size) are the unsigned codes q_x.
// `row_fp32` is scratch of k floats that receives x converted to fp32.
template <typename Element, typename OnGroup>
void quantize_activation_row(const Element* x, int64_t k, int group_size, int act_bits, float* row_fp32,
                             uint8_t* group_codes, OnGroup&& on_group) {
  for (int64_t i = 0; i < k; ++i) row_fp32[i] = to_float(x[i]);
  for (int64_t g = 0; g < k / group_size; ++g) {
    const float* v = row_fp32 + g * group_size;
    float group_min = 0.0f;
    float group_max = 0.0f;
    bool nonfinite = false;
    for (int i = 0; i < group_size; ++i) {
      nonfinite |= !std::isfinite(v[i]);
      group_min = std::fmin(group_min, v[i]);
      group_max = std::fmax(group_max, v[i]);
    }
    const ActivationGroupParams params = activation_group_params(group_min, group_max, act_bits, nonfinite);
    for (int i = 0; i < group_size; ++i) group_codes[i] = static_cast<uint8_t>(activation_code(v[i], params, act_bits));
    on_group(g, params, static_cast<const uint8_t*>(group_codes));
  }
}

}  // namespace dyq::cpu
