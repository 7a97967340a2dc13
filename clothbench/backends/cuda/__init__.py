"""CUDA through CuPy RawKernel: Verlet (verlet.py; launch.py: kernel shapes and buffers; cpu.py:
the CPU build the tests run; kernels/verlet_cloth.cu; docs/cuda.md)."""
