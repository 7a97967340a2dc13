"""The model: what is simulated, written once for every backend. The scene (cloth, colliders,
pins, the scene file's reader), the solver settings (Verlet, PBD and VBD's steps and their
refusals), the constraints of the 12-spring stencil, the colliders (analytic kinds in one
table, meshes, motion, self-contact), and the numbers every kernel takes, computed in float64
and rounded once (kernel_inputs). It imports nothing of clothbench's above it: backends,
harness, analysis, reports and the applications all read it.
"""
