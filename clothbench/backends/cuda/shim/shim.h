// Just enough of CUDA for g++ to compile an unmodified kernels/*.cu and run it on the CPU:
//
//   g++ -std=c++17 -O2 -ffp-contract=off -x c++ -include shim.h -DCLOTH_GENERIC kernels/verlet_cloth.cu
//
// (or, instead of -DCLOTH_GENERIC, the scene's -D switches:
// clothbench.backends.cuda.verlet.kernel_defines).
// Threads run one after another, so a kernel must not use __shared__ or __syncthreads()
// (ours read the input buffers and write only their own particle of the output buffers).
// Keep -ffp-contract=off: g++ fuses a*b+c silently under -march=native / -mfma, and the
// strict kernel is only bit-exact with NumPy when every operation is rounded on its own.
// With -Wall add -Wno-unknown-pragmas: g++ ignores CUDA's `#pragma unroll` (and says so).
#pragma once

#include <cmath>
#include <cstddef>
#include <type_traits>
#include <utility>

#define __global__
#define __device__
#define __host__
#define __constant__
#define __forceinline__ inline
#define __launch_bounds__(...)
// __restrict__ is already a g++ keyword.

struct uint3 {
    unsigned x, y, z;
};

struct dim3 {
    unsigned x, y, z;
    constexpr dim3(unsigned x_ = 1, unsigned y_ = 1, unsigned z_ = 1) : x(x_), y(y_), z(z_) {}
};

struct float3 {
    float x, y, z;
};

struct alignas(16) float4 {  // CUDA's float4 is 16-byte aligned too
    float x, y, z, w;
};

inline float3 make_float3(float x, float y, float z) { return float3{x, y, z}; }
inline float4 make_float4(float x, float y, float z, float w) { return float4{x, y, z, w}; }

// sqrtf (from <cmath>) is correctly rounded, as on the GPU without fast math. The GPU's
// rsqrtf is approximate; 1/sqrt is the nearest portable stand-in (fast mode only).
inline float rsqrtf(float x) { return 1.0f / std::sqrt(x); }

// The built-in variables, set by launch() before each thread runs.
inline uint3 threadIdx, blockIdx;
inline dim3 blockDim, gridDim;

// kernel<<<grid, block>>>(args...), one thread at a time.
template <typename... Params, typename... Args>
void launch(dim3 grid, dim3 block, void (*kernel)(Params...), Args... args)
{
    gridDim = grid;
    blockDim = block;
    for (unsigned bz = 0; bz < grid.z; ++bz)
        for (unsigned by = 0; by < grid.y; ++by)
            for (unsigned bx = 0; bx < grid.x; ++bx)
                for (unsigned tz = 0; tz < block.z; ++tz)
                    for (unsigned ty = 0; ty < block.y; ++ty)
                        for (unsigned tx = 0; tx < block.x; ++tx) {
                            blockIdx = uint3{bx, by, bz};
                            threadIdx = uint3{tx, ty, tz};
                            kernel(args...);
                        }
}

namespace cuda_shim {

// One letter per parameter type, so the caller can check its argument list against the
// kernel's signature (a real GPU launch would reinterpret mismatched bytes silently).
template <typename T>
constexpr char type_code()
{
    if constexpr (std::is_pointer_v<T>) return 'p';
    else if constexpr (std::is_same_v<T, float>) return 'f';
    else if constexpr (std::is_same_v<T, int>) return 'i';
    else if constexpr (std::is_same_v<T, unsigned>) return 'u';
    else return '?';
}

template <typename... Params>
const char* signature(void (*)(Params...))
{
    static const char codes[] = {type_code<Params>()..., '\0'};
    return codes;
}

template <typename... Params, std::size_t... I>
void launch_unpacked(dim3 grid, dim3 block, void (*kernel)(Params...), void** params,
                     std::index_sequence<I...>)
{
    launch(grid, block, kernel, *static_cast<std::remove_cv_t<Params>*>(params[I])...);
}

// cuLaunchKernel's argument form: params[i] points at the value of parameter i. This is
// what CuPy builds from a RawKernel call's args tuple, so ctypes can build the same.
template <typename... Params>
int launch_params(dim3 grid, dim3 block, void (*kernel)(Params...), void** params, int count)
{
    if (count != static_cast<int>(sizeof...(Params))) return -1;
    launch_unpacked(grid, block, kernel, params, std::index_sequence_for<Params...>{});
    return 0;
}

}  // namespace cuda_shim

// C entry points for ctypes, one pair per kernel:
//   int  <kernel>_launch(unsigned grid, unsigned block, void** params, int count)  (-1: wrong count)
//   const char* <kernel>_signature()                                               (e.g. "ppppif")
#define CUDA_SHIM_EXPORT(kernel)                                                            \
    extern "C" int kernel##_launch(unsigned grid, unsigned block, void** params, int count) \
    {                                                                                       \
        return cuda_shim::launch_params(dim3(grid), dim3(block), kernel, params, count);    \
    }                                                                                       \
    extern "C" const char* kernel##_signature() { return cuda_shim::signature(kernel); }
