"""NumPy: the reference, float32 or float64, Verlet (verlet.py) and PBD (pbd.py)."""
