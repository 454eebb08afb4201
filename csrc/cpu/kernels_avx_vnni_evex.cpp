// The AVX-VNNI path's kernels EVEX-encoded, for CPUs with AVX-512 VNNI and VL but not AVX-VNNI (Cascade
// Lake, Ice Lake, Zen 4): the same source as kernels_avx_vnni.cpp, so that those CPUs run and test the path.
#define DYQ_CPU_ISA_AVX_VNNI_EVEX 1

#include "gemm/gemm_cpu_avx2.h"

#include "cpu/kernel_entries.h"
