// The AVX-512 VNNI path with AVX512-BF16 (Cooper Lake, Sapphire Rapids, Zen 4 and later): the AVX-512
// kernels, with the W4A16 fallback on bf16 dot products (vdpbf16ps), compiled in its target region
// (cpu/isa_region.h).
#define DYQ_CPU_ISA_AVX512_BF16 1

#include "gemm/gemm_cpu_avx512.h"

#include "cpu/kernel_entries.h"
