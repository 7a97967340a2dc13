"""OpenGL through moderngl: the context and shared GL host code (context.py), the fragment-shader
Verlet step (fragment.py), the compute-shader Verlet step (compute.py) and PBD (compute_pbd.py)."""
