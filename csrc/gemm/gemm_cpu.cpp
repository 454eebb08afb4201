// The W4A2 / W4A4 / W4A8 / W4A16 GEMM on the CPU (docs/numerics.md, section 3): the kernel of the path
// that cpu/cpu_isa.h chose for this CPU.
#include "gemm/gemm_cpu.h"

#include "cpu/cpu_isa.h"

namespace dyq::cpu {

bool gemm(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias,
          int64_t m, int64_t n, int64_t k, int group_size, int act_bits, void* out) {
  return active_cpu_path().kernels->gemm(x, dtype, qweight, scales, bias, m, n, k, group_size, act_bits, out);
}

}  // namespace dyq::cpu
