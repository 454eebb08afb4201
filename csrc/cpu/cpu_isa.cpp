// The dispatch table of cpu/cpu_isa.h.
#include "cpu/cpu_isa.h"

#if defined(__x86_64__)
#include <cpuid.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include <cstdlib>
#include <stdexcept>
#include <string>

namespace dyq::cpu {

#if defined(__x86_64__)
namespace avx512_amx {
extern const CpuKernelSet kernels;
}
namespace avx512_bf16 {
extern const CpuKernelSet kernels;
}
namespace avx512 {
extern const CpuKernelSet kernels;
}
namespace avx_vnni {
extern const CpuKernelSet kernels;
}
namespace avx_vnni_evex {
extern const CpuKernelSet kernels;
}
namespace avx2 {
extern const CpuKernelSet kernels;
}
#endif
namespace portable {
extern const CpuKernelSet kernels;
}

namespace {

#if defined(__x86_64__)
// __builtin_cpu_supports also checks that the OS saves the YMM / ZMM state (XGETBV).
bool avx512_runs_here() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
         __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl") &&
         __builtin_cpu_supports("avx512vnni") && __builtin_cpu_supports("avx512vbmi");
}

bool avx512_bf16_runs_here() { return avx512_runs_here() && __builtin_cpu_supports("avx512bf16"); }

// CPUID leaf 7 reports AMX-BF16 (EDX bit 22), AMX-TILE (bit 24) and AMX-INT8 (bit 25). Linux then grants a process the tile
// data state only on request (arch_prctl ARCH_REQ_XCOMP_PERM for XFEATURE_XTILEDATA); without it the first
// tile instruction faults. Asked once, when the paths are first listed.
bool amx_runs_here() {
  static const bool runs = [] {
    unsigned eax = 0, ebx = 0, ecx = 0, edx = 0;
    if (!avx512_bf16_runs_here() || !__get_cpuid_count(7, 0, &eax, &ebx, &ecx, &edx)) return false;
    if ((edx & (1u << 22)) == 0 || (edx & (1u << 24)) == 0 || (edx & (1u << 25)) == 0) return false;
    constexpr long kArchReqXcompPerm = 0x1023, kXfeatureXtiledata = 18;
    return syscall(SYS_arch_prctl, kArchReqXcompPerm, kXfeatureXtiledata) == 0;
  }();
  return runs;
}

bool avx2_runs_here() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("f16c");
}

// CPUID leaf 7, subleaf 1 reports AVX-VNNI, the VEX-encoded vpdpbusd (EAX bit 4).
bool has_avx_vnni() {
  unsigned eax = 0, ebx = 0, ecx = 0, edx = 0;
  return __get_cpuid_count(7, 1, &eax, &ebx, &ecx, &edx) && (eax & (1u << 4)) != 0;
}

// The AVX-VNNI path runs in its VEX encoding, or in its EVEX one on CPUs with AVX-512 VNNI and VL.
bool avx_vnni_runs_here() {
  return avx2_runs_here() && (has_avx_vnni() || (__builtin_cpu_supports("avx512f") &&
                                                 __builtin_cpu_supports("avx512vl") &&
                                                 __builtin_cpu_supports("avx512vnni")));
}

const CpuKernelSet* avx_vnni_kernels() { return has_avx_vnni() ? &avx_vnni::kernels : &avx_vnni_evex::kernels; }
#endif

bool portable_runs_here() { return true; }

std::string path_names() {
  std::string names;
  for (const CpuPath& path : cpu_paths()) names += (names.empty() ? "" : ", ") + std::string(path.name);
  return names;
}

const CpuPath& choose_path() {
  const char* forced = std::getenv("DYQ_CPU_ISA");
  if (forced == nullptr || *forced == '\0') return *runnable_cpu_paths().front();
  for (const CpuPath& path : cpu_paths()) {
    if (path.name != std::string(forced)) continue;
    if (!path.runs_here()) {
      throw std::invalid_argument("DYQ_CPU_ISA=" + std::string(forced) + ": this CPU lacks " + path.features);
    }
    return path;
  }
  throw std::invalid_argument("DYQ_CPU_ISA=" + std::string(forced) + " is not one of this build's paths (" +
                              path_names() + ")");
}

}  // namespace

const std::vector<CpuPath>& cpu_paths() {
  // Best first. Another path is one entry here, one
  // cpu/kernels_<isa>.cpp and its name and target in cpu/isa_region.h.
  static const std::vector<CpuPath> paths = {
#if defined(__x86_64__)
      {"amx", "AMX-TILE, AMX-INT8 and AMX-BF16 (granted by the OS), with AVX-512 VNNI, VBMI and BF16", amx_runs_here,
       &avx512_amx::kernels},
      {"avx512_bf16", "AVX-512 F/BW/DQ/VL with VNNI, VBMI and BF16", avx512_bf16_runs_here, &avx512_bf16::kernels},
      {"avx512", "AVX-512 F/BW/DQ/VL with VNNI and VBMI", avx512_runs_here, &avx512::kernels},
      {"avx_vnni", "AVX2 with FMA, F16C and 256-bit VNNI (AVX-VNNI, or AVX-512 VNNI with VL)", avx_vnni_runs_here,
       avx_vnni_kernels()},
      {"avx2", "AVX2 with FMA and F16C", avx2_runs_here, &avx2::kernels},
#endif
      {"portable", "nothing beyond the baseline", portable_runs_here, &portable::kernels},
  };
  return paths;
}

std::vector<const CpuPath*> runnable_cpu_paths() {
  std::vector<const CpuPath*> runnable;
  for (const CpuPath& path : cpu_paths()) {
    if (path.runs_here()) runnable.push_back(&path);
  }
  return runnable;
}

const CpuPath& active_cpu_path() {
  static const CpuPath& active = choose_path();
  return active;
}

}  // namespace dyq::cpu
