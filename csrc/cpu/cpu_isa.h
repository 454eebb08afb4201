// The instruction-set paths of dyq's CPU kernels and the one table that picks one at run time.
//
// The build compiles every path its processor family has (cpu/kernels_<isa>.cpp, each in a target region:
// cpu/isa_region.h), so one binary runs on any x86-64 or aarch64 CPU at the speed of the best path that
// CPU can execute. DYQ_CPU_ISA=<name> forces a path (for tests and measurements).
#pragma once

#include <cstdint>
#include <vector>

#include "common/format.h"

namespace dyq::cpu {

// The kernels of one path, with the arguments of dyq::cpu::gemm, dyq::cpu::quantize_activations,
// dyq::cpu::hadamard_transform and dyq::cpu::rms_norm.
struct CpuKernelSet {
  bool (*gemm)(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias,
               int64_t m, int64_t n, int64_t k, int group_size, int act_bits, void* out);
  void (*quantize_activations)(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                               uint8_t* packed, float* scales, uint8_t* zeros);
  // The name of the kernel that gemm runs for these arguments (benchmarks record it).
  const char* (*gemm_kernel)(int64_t m, int64_t k, int group_size, int act_bits);
  void (*hadamard_transform)(const void* x, ScalarType dtype, const float* signs, const float* left, int64_t rows,
                             int64_t n, int64_t m, void* out);
  void (*rms_norm)(const void* x, ScalarType dtype, const void* weight, int64_t rows, int64_t n, float eps, void* out);
};

struct CpuPath {
  const char* name;      // the DYQ_CPU_ISA value that forces it
  const char* features;  // what the CPU must have, for messages
  bool (*runs_here)();
  const CpuKernelSet* kernels;
};

// Every path compiled into this build, best first.
const std::vector<CpuPath>& cpu_paths();

// The paths this CPU can execute, best first (the portable one always).
std::vector<const CpuPath*> runnable_cpu_paths();

// The path the kernels run: the one DYQ_CPU_ISA names, else the best one this CPU can execute. Chosen on
// first use; throws std::invalid_argument while DYQ_CPU_ISA names no path or one this CPU cannot execute.
const CpuPath& active_cpu_path();

}  // namespace dyq::cpu
