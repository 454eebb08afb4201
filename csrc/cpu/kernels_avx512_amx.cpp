// The AMX path (Sapphire Rapids and later): the AVX512-BF16 path with the GEMM of many activation rows on
// AMX tiles, AMX-INT8 at act_bits 2/4/8 and AMX-BF16 at 16 (gemm/gemm_cpu_amx.h), compiled in its target
// region (cpu/isa_region.h).
#define DYQ_CPU_ISA_AVX512_AMX 1

#include "gemm/gemm_cpu_avx512.h"

#include "cpu/kernel_entries.h"
