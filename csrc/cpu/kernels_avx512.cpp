// The AVX-512 VNNI path (Ice Lake, Sapphire Rapids, Zen 4 and later), compiled in its target region
// (cpu/isa_region.h).
#define DYQ_CPU_ISA_AVX512 1

#include "gemm/gemm_cpu_avx512.h"

#include "cpu/kernel_entries.h"
