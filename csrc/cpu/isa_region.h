// The instruction-set region of a CPU kernel file: every kernel that uses an instruction set beyond the
// baseline is compiled in a target region of a translation unit of its own (cpu/kernels_<isa>.cpp) and
// lives in the namespace of that instruction set, dyq::cpu::<isa>, so that one binary holds every path
// and cpu/cpu_isa.cpp picks one at run time.
//
// Why a region rather than -m flags on the file: with flags, the std::vector, std::function and Eigen
// functions that every kernel file instantiates would each carry that file's instructions, and the linker
// keeps one copy of each for the whole library, so an AVX-512 copy of a std::vector fill could end up
// on the AVX2 path. In a region only the functions defined inside it get the instructions; templates
// from headers included before it (std, Eigen, dyq's common/ and parallel/) keep the baseline ones and
// may still be inlined into the kernels. Headers that use DYQ_ISA_BEGIN therefore include everything
// they need first.
//
// A kernel file defines one of DYQ_CPU_ISA_AVX512_AMX / DYQ_CPU_ISA_AVX512_BF16 / DYQ_CPU_ISA_AVX512 /
// DYQ_CPU_ISA_AVX_VNNI / DYQ_CPU_ISA_AVX_VNNI_EVEX / DYQ_CPU_ISA_AVX2 before its first include; without any
// it is the portable path (plain C++ and Eigen at the compiler's baseline: SSE2 on x86-64, NEON on aarch64).
// The AMX and BF16 paths are the AVX-512 one with more instructions: they define DYQ_CPU_ISA_AVX512 too (the
// family the shared x86 helpers test) and DYQ_AVX512_HAS_BF16 / DYQ_AVX512_HAS_AMX for the kernels that use
// them. Likewise the AVX-VNNI path is the AVX2 one with 256-bit VNNI dot products (DYQ_CPU_ISA_AVX2 and
// DYQ_AVX2_HAS_VNNI), compiled twice: VEX-encoded for the CPUs with AVX-VNNI (Alder Lake and later, the
// Gracemont cores of the N100), and the same source EVEX-encoded (DYQ_AVX2_VNNI_EVEX) for CPUs with AVX-512
// VNNI, which lack the VEX form until Sapphire Rapids and Zen 5, so that they run and test this path too.
// DYQ_ISA_NAME is the path's DYQ_CPU_ISA value (both encodings are "avx_vnni").
#if defined(DYQ_CPU_ISA_AVX512_AMX)
#define DYQ_CPU_ISA_AVX512 1
#define DYQ_AVX512_HAS_BF16 1
#define DYQ_AVX512_HAS_AMX 1
#define DYQ_ISA_NAMESPACE avx512_amx
#define DYQ_ISA_NAME "amx"
#define DYQ_ISA_TARGET \
  "avx512f,avx512bw,avx512dq,avx512vl,avx512vnni,avx512vbmi,avx512bf16,amx-tile,amx-int8,amx-bf16,avx2,fma,f16c"
#elif defined(DYQ_CPU_ISA_AVX512_BF16)
#define DYQ_CPU_ISA_AVX512 1
#define DYQ_AVX512_HAS_BF16 1
#define DYQ_ISA_NAMESPACE avx512_bf16
#define DYQ_ISA_NAME "avx512_bf16"
#define DYQ_ISA_TARGET "avx512f,avx512bw,avx512dq,avx512vl,avx512vnni,avx512vbmi,avx512bf16,avx2,fma,f16c"
#elif defined(DYQ_CPU_ISA_AVX512)
#define DYQ_ISA_NAMESPACE avx512
#define DYQ_ISA_NAME "avx512"
#define DYQ_ISA_TARGET "avx512f,avx512bw,avx512dq,avx512vl,avx512vnni,avx512vbmi,avx2,fma,f16c"
#elif defined(DYQ_CPU_ISA_AVX_VNNI)
#define DYQ_CPU_ISA_AVX2 1
#define DYQ_AVX2_HAS_VNNI 1
#define DYQ_ISA_NAMESPACE avx_vnni
#define DYQ_ISA_NAME "avx_vnni"
#define DYQ_ISA_TARGET "avx2,fma,f16c,avxvnni"
#elif defined(DYQ_CPU_ISA_AVX_VNNI_EVEX)
#define DYQ_CPU_ISA_AVX2 1
#define DYQ_AVX2_HAS_VNNI 1
#define DYQ_AVX2_VNNI_EVEX 1
#define DYQ_ISA_NAMESPACE avx_vnni_evex
#define DYQ_ISA_NAME "avx_vnni"
#define DYQ_ISA_TARGET "avx2,fma,f16c,avx512f,avx512vl,avx512vnni,prefer-vector-width=256"
#elif defined(DYQ_CPU_ISA_AVX2)
#define DYQ_ISA_NAMESPACE avx2
#define DYQ_ISA_NAME "avx2"
#define DYQ_ISA_TARGET "avx2,fma,f16c"
#else
#define DYQ_ISA_NAMESPACE portable
#define DYQ_ISA_NAME "portable"
#endif

#if defined(DYQ_ISA_TARGET)
#include <immintrin.h>
#define DYQ_PRAGMA_STRING(text) _Pragma(#text)
#define DYQ_PRAGMA(text) DYQ_PRAGMA_STRING(text)  // expands DYQ_ISA_TARGET before quoting
#if defined(__clang__)
#define DYQ_ISA_BEGIN DYQ_PRAGMA(clang attribute push(__attribute__((target(DYQ_ISA_TARGET))), apply_to = function))
#define DYQ_ISA_END DYQ_PRAGMA(clang attribute pop)
#else
#define DYQ_ISA_BEGIN DYQ_PRAGMA(GCC push_options) DYQ_PRAGMA(GCC target(DYQ_ISA_TARGET))
#define DYQ_ISA_END DYQ_PRAGMA(GCC pop_options)
#endif
#else
#define DYQ_ISA_BEGIN
#define DYQ_ISA_END
#endif
