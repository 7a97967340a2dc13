/* body_args.cl: the extra kernel arguments of a scene with meshes, motion or attached pins,
 * for verlet_cloth.cl, pbd_cloth.cl and vbd_cloth.cl (the host resolves the #include:
 * clothbench/kernel_source.py resolve_includes). STEP_ARG, MESH_ARG and PIN_ARG go in a
 * kernel's parameters, STEP_PASS, MESH_PASS and PIN_PASS through the helpers that take them. */
#ifndef CLOTH_MESHES
#define CLOTH_MESHES 0
#endif
#define MESH_ROWS 6 /* collider-table rows per mesh: pose, margins, box (collide_mesh.cl) */
#if CLOTH_MESHES > 0
#define MESH_ARG , __global const float4 *mesh_geometry, __global const int *mesh_ints
#define MESH_PASS , mesh_geometry, mesh_ints
#else
#define MESH_ARG
#define MESH_PASS
#endif
#ifdef CLOTH_ATTACHED_PINS
#define PIN_ARG , __global const int *pin_slot, __global const float *pin_target
#define PIN_PASS , pin_slot, pin_target
#define PIN_STEP_TARGETS(first) (pin_target += 3 * CLOTH_PINS * (first)) /* this step's */
#else
#define PIN_ARG
#define PIN_PASS
#define PIN_STEP_TARGETS(first)
#endif
#ifdef CLOTH_PER_STEP /* the step (or substep) index of a launch that does one */
#define STEP_ARG , const int step
#define STEP_PASS , step
#else
#define STEP_ARG
#define STEP_PASS
#endif
