# The torch-free CUDA kernel library (pointers, sizes, a stream), compiled for every target architecture.
# Included by the top-level CMakeLists.txt when DYQ_CUDA is ON; the torch glue is in cuda_glue.cmake.
if(NOT DEFINED CMAKE_CUDA_ARCHITECTURES)
  # A100 (sm_80), RTX 30xx / A10 / A6000 (sm_86), Jetson Orin (sm_87), Ada (sm_89), H100/H200 (sm_90a).
  # Real code only: no PTX to JIT on other devices.
  set(CMAKE_CUDA_ARCHITECTURES "80-real;86-real;87-real;89-real;90a-real")
endif()
enable_language(CUDA)
find_package(CUDAToolkit REQUIRED)
# One line that says what the kernel library targets (.ci/run prints it).
message(STATUS "dyq CUDA architectures: ${CMAKE_CUDA_ARCHITECTURES}")

add_library(dyq_cuda_kernels STATIC
  csrc/weight/weight_pack_cuda.cu
  csrc/activation/act_quant_cuda.cu
  csrc/activation/hadamard_cuda.cu
  csrc/activation/rms_norm_cuda.cu
  csrc/gemm/gemm_decode_cuda.cu
  csrc/gemm/gemm_prefill_cuda.cu
  csrc/gemm/gemm_cuda.cu
)
target_include_directories(dyq_cuda_kernels PUBLIC ${CMAKE_CURRENT_SOURCE_DIR}/csrc)
target_link_libraries(dyq_cuda_kernels PUBLIC CUDA::cudart)
set_target_properties(dyq_cuda_kernels PROPERTIES
  POSITION_INDEPENDENT_CODE ON
  CUDA_STANDARD 17
  CUDA_STANDARD_REQUIRED ON)
# IEEE division and round-to-nearest conversions are part of the numerics (docs/numerics.md): never
# --use_fast_math. -Xptxas=-v prints each kernel's registers, shared memory and spills.
target_compile_options(dyq_cuda_kernels PRIVATE
  $<$<COMPILE_LANGUAGE:CUDA>:-O3 --expt-relaxed-constexpr -Xptxas=-warn-spills -lineinfo>)
