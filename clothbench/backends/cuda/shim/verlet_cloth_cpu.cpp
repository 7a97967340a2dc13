// The CPU build of kernels/verlet_cloth.cu, for the tests (clothbench/backends/cuda/cpu.py): the
// kernel source as it is (compiled with -include shim.h and -I kernels/, and the -D switches of
// the GPU build: -DCLOTH_STRICT and clothbench.backends.cuda.verlet.kernel_defines), plus C
// entry points for ctypes that take cuLaunchKernel's argument form. See shim.h.
#include "verlet_cloth.cu"

CUDA_SHIM_DYNAMIC_SHARED(float, cloth_shared)
CUDA_SHIM_EXPORT(verlet_step)
CUDA_SHIM_EXPORT_WITH_BARRIERS(verlet_steps)
#ifdef CLOTH_SELF_COLLISION
CUDA_SHIM_EXPORT(self_cell_keys)
CUDA_SHIM_EXPORT(self_sort_stage)
CUDA_SHIM_EXPORT(self_collision)
#endif
