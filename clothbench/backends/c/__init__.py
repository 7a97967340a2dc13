"""Native C with OpenMP: the Verlet step (verlet.py, kernels/verlet_cloth.c) and VBD (vbd.py,
kernels/vbd_cloth.c), built at first use by the system C compiler (clothbench/native.py)."""
