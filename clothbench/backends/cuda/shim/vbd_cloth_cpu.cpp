// The CPU build of kernels/vbd_cloth.cu, for the tests (clothbench/backends/cuda/cpu.py): the
// kernel source as it is (compiled with -include shim.h and -I kernels/, and the -D switches of
// the GPU build: -DCLOTH_STRICT and clothbench.backends.cuda.vbd.vbd_defines), plus C entry
// points for ctypes that take cuLaunchKernel's argument form. See shim.h.
#include "vbd_cloth.cu"

CUDA_SHIM_EXPORT(vbd_predict)
CUDA_SHIM_EXPORT(vbd_sweep)
CUDA_SHIM_EXPORT(vbd_chebyshev)
CUDA_SHIM_EXPORT(vbd_collide)
CUDA_SHIM_EXPORT(vbd_update)
#ifdef CLOTH_SELF_COLLISION
CUDA_SHIM_EXPORT(self_cell_keys)
CUDA_SHIM_EXPORT(self_sort_stage)
CUDA_SHIM_EXPORT(self_collision)
#endif
