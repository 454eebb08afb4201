// The online Hadamard rotation (activation/hadamard_cpu.h): the kernel of the path that cpu/cpu_isa.h chose
// for this CPU (the row transform itself: activation/hadamard_cpu_row.h).
#include "activation/hadamard_cpu.h"

#include "cpu/cpu_isa.h"

namespace dyq::cpu {

void hadamard_transform(const void* x, ScalarType dtype, const float* signs, const float* left, int64_t rows,
                        int64_t n, int64_t m, void* out) {
  active_cpu_path().kernels->hadamard_transform(x, dtype, signs, left, rows, n, m, out);
}

}  // namespace dyq::cpu
