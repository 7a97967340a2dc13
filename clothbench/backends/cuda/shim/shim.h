// Just enough of CUDA for g++ to compile an unmodified kernels/*.cu and run it on the CPU:
//
//   g++ -std=c++17 -O2 -ffp-contract=off -x c++ -include shim.h -DCLOTH_GENERIC kernels/verlet_cloth.cu
//
// (or, instead of -DCLOTH_GENERIC, the scene's -D switches:
// clothbench.backends.cuda.verlet.kernel_defines).
//
// The threads of a block run one at a time, on one CPU thread. A kernel exported with
// CUDA_SHIM_EXPORT must not call __syncthreads(): its threads run one after another, each to
// its end (ours read the input buffers and write only their own particle of the outputs).
// One exported with CUDA_SHIM_EXPORT_WITH_BARRIERS runs each thread of a block as a fiber
// (ucontext): __syncthreads() suspends the calling thread until every thread of the block has
// reached it, as on the GPU, so the code between two barriers runs for all threads before any
// thread runs past the second. `<kernel>_schedule(seed)` shuffles the order the threads run
// in between barriers (0: in order), so a test can show that the result does not depend on
// it: a kernel whose threads race within a phase would. A barrier some threads of the block
// never reach (they returned) is an error, as CUDA leaves it undefined.
// Dynamic shared memory: `extern __shared__ T name[];` in the kernel file, and
// CUDA_SHIM_DYNAMIC_SHARED(T, name) once after including it (up to 256 KiB, more than any
// GPU gives a block); every launch fills the bytes it asks for with NaN first, as a GPU's
// shared memory starts undefined. Static `__shared__` arrays are not supported.
// Keep -ffp-contract=off: g++ fuses a*b+c silently under -march=native / -mfma, and the
// strict kernel is only bit-exact with NumPy when every operation is rounded on its own.
// With -Wall add -Wno-unknown-pragmas: g++ ignores CUDA's `#pragma unroll` (and says so).
#pragma once

#include <ucontext.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <utility>
#include <vector>

#define __global__
#define __device__
#define __host__
#define __constant__
#define __forceinline__ inline
#define __launch_bounds__(...)
#define __shared__  // for `extern __shared__` only: see CUDA_SHIM_DYNAMIC_SHARED
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

// CUDA's bit reinterpretation (e.g. +inf as __int_as_float(0x7f800000): NVRTC has no INFINITY).
inline float __int_as_float(int i)
{
    float f;
    std::memcpy(&f, &i, sizeof f);
    return f;
}

// sqrtf (from <cmath>) is correctly rounded, as on the GPU without fast math. The GPU's
// rsqrtf is approximate; 1/sqrt is the nearest portable stand-in (fast mode only).
inline float rsqrtf(float x) { return 1.0f / std::sqrt(x); }

using std::isfinite;  // CUDA's isfinite(float) is global

// The built-in variables, set by launch() before each thread runs.
inline uint3 threadIdx, blockIdx;
inline dim3 blockDim, gridDim;

namespace cuda_shim {

// Launch errors, returned by <kernel>_launch.
enum Status : int {
    ok = 0,
    wrong_argument_count = -1,
    barrier_without_fibers = -2,  // __syncthreads() in a kernel exported with CUDA_SHIM_EXPORT
    barrier_not_reached = -3,     // some threads of the block returned, others wait at a barrier
    too_much_shared_memory = -4,  // more dynamic shared memory than CUDA_SHIM_DYNAMIC_SHARED holds
};

// The dynamic shared memory, registered by CUDA_SHIM_DYNAMIC_SHARED.
inline unsigned char* shared_storage = nullptr;
inline std::size_t shared_capacity = 0;

struct SharedRegistration {
    SharedRegistration(void* storage, std::size_t bytes)
    {
        shared_storage = static_cast<unsigned char*>(storage);
        shared_capacity = bytes;
    }
};

// The fibers of the block being run: one per thread, each with its own stack.
struct Fiber {
    ucontext_t context;
    uint3 thread;
    bool done;
};

inline constexpr std::size_t fiber_stack_bytes = 64 * 1024;
inline std::vector<Fiber> fibers;
inline std::vector<unsigned char> fiber_stacks;
inline ucontext_t scheduler;
inline Fiber* running = nullptr;  // null: not inside a fiber
inline void (*fiber_body)(void*) = nullptr;
inline void* fiber_closure = nullptr;
inline int status = ok;
inline std::uint64_t schedule_seed = 0;  // 0: threads in order; else shuffled between barriers

inline void fiber_main()
{
    fiber_body(fiber_closure);
    running->done = true;  // returns to uc_link, the scheduler
}

inline void syncthreads()
{
    if (running == nullptr) {
        status = barrier_without_fibers;  // cannot suspend: the launch reports it
        return;
    }
    swapcontext(&running->context, &scheduler);
}

// A fiber that will start at fiber_main on its own stack. Not inlined: getcontext returns
// twice, and the caller's loop variables would be at risk (-Wclobbered).
[[gnu::noinline]] inline void prepare_fiber(Fiber& f, uint3 thread, unsigned char* stack)
{
    f.thread = thread;
    f.done = false;
    getcontext(&f.context);
    f.context.uc_stack.ss_sp = stack;
    f.context.uc_stack.ss_size = fiber_stack_bytes;
    f.context.uc_link = &scheduler;
    makecontext(&f.context, fiber_main, 0);
}

// The order the threads run in, for one phase (between two barriers).
inline void phase_order(std::vector<unsigned>& order, std::uint64_t& state)
{
    for (unsigned t = 0; t < order.size(); ++t) order[t] = t;
    if (schedule_seed == 0) return;
    for (std::size_t t = order.size(); t > 1; --t) {  // Fisher-Yates with a 64-bit LCG
        state = state * 6364136223846793005ULL + 1442695040888963407ULL;
        std::swap(order[t - 1], order[(state >> 33) % t]);
    }
}

// One block as fibers, phase after phase: each phase resumes every thread once, in the
// phase's order, and each runs until its next barrier or its end.
template <typename Body>
int run_block_as_fibers(dim3 block, Body& body)
{
    const std::size_t count = std::size_t(block.x) * block.y * block.z;
    fibers.resize(count);
    fiber_stacks.resize(count * fiber_stack_bytes);
    fiber_body = [](void* closure) { (*static_cast<Body*>(closure))(); };
    fiber_closure = &body;
    std::size_t t = 0;
    for (unsigned tz = 0; tz < block.z; ++tz)
        for (unsigned ty = 0; ty < block.y; ++ty)
            for (unsigned tx = 0; tx < block.x; ++tx, ++t)
                prepare_fiber(fibers[t], uint3{tx, ty, tz}, &fiber_stacks[t * fiber_stack_bytes]);
    std::vector<unsigned> order(count);
    std::uint64_t state = schedule_seed;
    for (;;) {
        phase_order(order, state);
        std::size_t finished = 0;
        for (unsigned index : order) {
            Fiber& f = fibers[index];
            threadIdx = f.thread;
            running = &f;
            swapcontext(&scheduler, &f.context);
            running = nullptr;
            finished += f.done;
        }
        if (finished == count) return ok;
        if (finished != 0) return barrier_not_reached;
    }
}

// kernel<<<grid, block, shared_bytes>>>(args...), one thread at a time; with barriers, each
// block's threads as fibers.
template <typename... Params, typename... Args>
int launch(dim3 grid, dim3 block, std::size_t shared_bytes, bool barriers, void (*kernel)(Params...),
           Args... args)
{
    if (shared_bytes > shared_capacity) return too_much_shared_memory;
    gridDim = grid;
    blockDim = block;
    status = ok;
    auto body = [&] { kernel(args...); };
    for (unsigned bz = 0; bz < grid.z; ++bz)
        for (unsigned by = 0; by < grid.y; ++by)
            for (unsigned bx = 0; bx < grid.x; ++bx) {
                blockIdx = uint3{bx, by, bz};
                if (shared_bytes) std::memset(shared_storage, 0xff, shared_bytes);  // NaN floats
                if (barriers) {
                    const int done = run_block_as_fibers(block, body);
                    if (done != ok) return done;
                    continue;
                }
                for (unsigned tz = 0; tz < block.z; ++tz)
                    for (unsigned ty = 0; ty < block.y; ++ty)
                        for (unsigned tx = 0; tx < block.x; ++tx) {
                            threadIdx = uint3{tx, ty, tz};
                            body();
                        }
                if (status != ok) return status;
            }
    return status;
}

// One letter per parameter type, so the caller can check its argument list against the
// kernel's signature (a real GPU launch would reinterpret mismatched bytes silently).
// 'q' is a pointer to int (an int buffer), 'k' to unsigned long long (the self-collision pass's
// cell ids), 'p' any other pointer (float4 buffers).
template <typename T>
constexpr char type_code()
{
    if constexpr (std::is_pointer_v<T> && std::is_same_v<std::remove_cv_t<std::remove_pointer_t<T>>, int>) return 'q';
    else if constexpr (std::is_pointer_v<T> &&
                       std::is_same_v<std::remove_cv_t<std::remove_pointer_t<T>>, unsigned long long>) return 'k';
    else if constexpr (std::is_pointer_v<T>) return 'p';
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
int launch_unpacked(dim3 grid, dim3 block, std::size_t shared_bytes, bool barriers, void (*kernel)(Params...),
                    void** params, std::index_sequence<I...>)
{
    return launch(grid, block, shared_bytes, barriers, kernel,
                  *static_cast<std::remove_cv_t<Params>*>(params[I])...);
}

// cuLaunchKernel's argument form: params[i] points at the value of parameter i. This is
// what CuPy builds from a RawKernel call's args tuple, so ctypes can build the same.
template <typename... Params>
int launch_params(dim3 grid, dim3 block, std::size_t shared_bytes, bool barriers, void (*kernel)(Params...),
                  void** params, int count)
{
    if (count != static_cast<int>(sizeof...(Params))) return wrong_argument_count;
    return launch_unpacked(grid, block, shared_bytes, barriers, kernel, params,
                           std::index_sequence_for<Params...>{});
}

}  // namespace cuda_shim

inline void __syncthreads() { cuda_shim::syncthreads(); }

// The storage behind `extern __shared__ T name[];`, once per library.
#define CUDA_SHIM_DYNAMIC_SHARED(T, name)                                   \
    alignas(16) T name[256 * 1024 / sizeof(T)];                             \
    static cuda_shim::SharedRegistration name##_registration(name, sizeof name);

// C entry points for ctypes, one set per kernel:
//   int  <kernel>_launch(unsigned grid, unsigned block, unsigned shared_bytes, void** params, int count)
//        (0, or a cuda_shim::Status)
//   const char* <kernel>_signature()             (e.g. "ppppif"; 'q': an int buffer, 'p': a float4 one)
//   void <kernel>_schedule(unsigned long long seed)   (WITH_BARRIERS: thread order, 0 = in order)
#define CUDA_SHIM_EXPORT_AS(kernel, barriers)                                                     \
    extern "C" int kernel##_launch(unsigned grid, unsigned block, unsigned shared_bytes,          \
                                   void** params, int count)                                      \
    {                                                                                             \
        return cuda_shim::launch_params(dim3(grid), dim3(block), shared_bytes, barriers, kernel,  \
                                        params, count);                                           \
    }                                                                                             \
    extern "C" const char* kernel##_signature() { return cuda_shim::signature(kernel); }
#define CUDA_SHIM_EXPORT(kernel) CUDA_SHIM_EXPORT_AS(kernel, false)
#define CUDA_SHIM_EXPORT_WITH_BARRIERS(kernel)                                                    \
    CUDA_SHIM_EXPORT_AS(kernel, true)                                                             \
    extern "C" void kernel##_schedule(unsigned long long seed) { cuda_shim::schedule_seed = seed; }
