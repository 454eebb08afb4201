// The AMX tile loop on scalar tiles (gemm/gemm_cpu_amx_emulated.h), compiled at the baseline.
#include "gemm/gemm_cpu_amx_emulated.h"

#include <stdexcept>

#include "gemm/gemm_cpu_amx.h"

namespace dyq::cpu {

void amx_emulated_gemm(const float* x, const uint8_t* qweight, const float* scales, const float* bias, int64_t m,
                       int64_t n, int64_t k, int group_size, int act_bits, float* out) {
  using namespace portable;
  if (act_bits == 16) {
    amx_bf16_gemm<EmulatedTiles, ScalarAmxBf16Panel>(x, qweight, scales, bias, m, n, k, group_size, out);
  } else if (act_bits == 2 || act_bits == 4) {
    amx_int8_gemm<EmulatedTiles, AmxInt8Centered, ScalarAmxInt8Panel<AmxInt8Centered>>(x, qweight, scales, bias, m,
                                                                                      n, k, group_size, act_bits, out);
  } else if (act_bits == 8) {
    amx_int8_gemm<EmulatedTiles, AmxInt8, ScalarAmxInt8Panel<AmxInt8>>(x, qweight, scales, bias, m, n, k, group_size,
                                                                       act_bits, out);
  } else {
    throw std::invalid_argument("amx_emulated_gemm: act_bits must be 2, 4, 8 or 16");
  }
}

}  // namespace dyq::cpu
