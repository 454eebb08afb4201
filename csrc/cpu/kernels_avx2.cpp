// The AVX2 path (x86-64 from Haswell and Zen 1 on), compiled in its target region (cpu/isa_region.h).
#define DYQ_CPU_ISA_AVX2 1

#include "gemm/gemm_cpu_avx2.h"

#include "cpu/kernel_entries.h"
