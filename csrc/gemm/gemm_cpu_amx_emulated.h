// The AMX tile loop of gemm/gemm_cpu_amx.h with its tile operations emulated in scalar C++: the same
// blocking, tile shapes, panel layout and epilogue as the "amx" path, on any CPU. For tests: it is slow.
#pragma once

#include <cstdint>

namespace dyq::cpu {

// dyq::cpu::gemm's arguments (gemm/gemm_cpu.h) for fp32 x, bias and out: act_bits 2, 4 or 8 through the
// AMX-INT8 loop, 16 through the AMX-BF16 one.
void amx_emulated_gemm(const float* x, const uint8_t* qweight, const float* scales, const float* bias, int64_t m,
                       int64_t n, int64_t k, int group_size, int act_bits, float* out);

}  // namespace dyq::cpu
