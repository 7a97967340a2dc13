"""OpenCL through pyopencl: Verlet (verlet.py, kernels/verlet_cloth.cl) and PBD (pbd.py, kernels/pbd_cloth.cl)."""
