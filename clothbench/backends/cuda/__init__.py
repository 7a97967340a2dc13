"""CUDA through CuPy RawKernel: Verlet (verlet.py, kernels/verlet_cloth.cu)."""
