# The TORCH_LIBRARY_IMPL(dyq, CUDA, ...) registrations, added to _C only when torch is a CUDA build
# (a CPU wheel lacks c10/cuda and libtorch_cuda).
target_sources(_C PRIVATE csrc/torch/ops_cuda.cpp)
target_link_libraries(_C PRIVATE dyq_cuda_kernels CUDA::cudart)
target_compile_definitions(_C PRIVATE DYQ_WITH_CUDA)
