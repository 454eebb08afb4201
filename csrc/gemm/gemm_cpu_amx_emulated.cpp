// The AMX tile loop on scalar tiles (gemm/gemm_cpu_amx_emulated.h), compiled at the baseline.
#include "gemm/gemm_cpu_amx_emulated.h"

#include <stdexcept>

#include "gemm/gemm_cpu_amx.h"

namespace dyq::cpu {

void amx_emulated_gemm(const float* x, const uint8_t* qweight, const float* scales, const float* bias, int64_t m,
                       int64_t n, int64_t k, int group_size, int act_bits, float* out) {
  if (act_bits != 2 && act_bits != 4 && act_bits != 8) {
    throw std::invalid_argument("amx_emulated_gemm: act_bits must be 2, 4 or 8");
  }
  portable::amx_gemm<portable::EmulatedTiles>(x, qweight, scales, bias, m, n, k, group_size, act_bits, out);
}

}  // namespace dyq::cpu
