"""Collider geometry that needs more than a few numbers: triangle meshes (mesh.py: loading,
the documented clean-up rules, pseudo-normals, the host-built BVH) and rigid motion
(motion.py: velocities, keyframes, kinematic frames). The step that uses them is written in
docs/semantics.md ("Triangle mesh", "Moving colliders", "Pins attached to a body").
"""
