// Dynamic activation quantization with packed output (docs/numerics.md, section 2): the kernel of the
// path that cpu/cpu_isa.h chose for this CPU (the quantizer itself: activation/act_quant_cpu_row.h).
#include "activation/act_quant_cpu.h"

#include "cpu/cpu_isa.h"

namespace dyq::cpu {

void quantize_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                          uint8_t* packed, float* scales, uint8_t* zeros) {
  active_cpu_path().kernels->quantize_activations(x, dtype, m, k, group_size, act_bits, packed, scales, zeros);
}

}  // namespace dyq::cpu
