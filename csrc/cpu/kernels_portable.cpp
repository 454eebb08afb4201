// The portable path: plain C++ and Eigen at the compiler's baseline, for every CPU (cpu/cpu_isa.h).
#include "gemm/gemm_cpu_portable.h"

#include "cpu/kernel_entries.h"
