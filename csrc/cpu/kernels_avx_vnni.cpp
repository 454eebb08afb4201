// The AVX-VNNI path (Alder Lake and later, the N100's Gracemont cores): the AVX2 kernels with their integer
// dot products on VEX-encoded 256-bit vpdpbusd, compiled in its target region (cpu/isa_region.h).
#define DYQ_CPU_ISA_AVX_VNNI 1

#include "gemm/gemm_cpu_avx2.h"

#include "cpu/kernel_entries.h"
