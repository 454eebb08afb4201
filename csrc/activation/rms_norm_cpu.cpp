// RMSNorm of activation rows (activation/rms_norm_cpu.h): the kernel of the path that cpu/cpu_isa.h chose for
// this CPU (the row itself: activation/rms_norm_cpu_row.h).
#include "activation/rms_norm_cpu.h"

#include "cpu/cpu_isa.h"

namespace dyq::cpu {

void rms_norm(const void* x, ScalarType dtype, const void* weight, int64_t rows, int64_t n, float eps, void* out) {
  active_cpu_path().kernels->rms_norm(x, dtype, weight, rows, n, eps, out);
}

}  // namespace dyq::cpu
