/* collider_counts.cl: a specialised program's analytic collider counts, 0 where the host gives
 * none (-DCLOTH_SPHERES=... from the kinds table, clothbench/model/colliders/kinds.py), and the
 * rows they take at the head of the collider table, in the kinds' order; for verlet_cloth.cl,
 * pbd_cloth.cl and vbd_cloth.cl (the host resolves the #include: clothbench/kernel_source.py
 * resolve_includes). */
#ifndef CLOTH_SPHERES
#define CLOTH_SPHERES 0
#endif
#ifndef CLOTH_CYLINDERS
#define CLOTH_CYLINDERS 0
#endif
#ifndef CLOTH_BOXES
#define CLOTH_BOXES 0
#endif
#ifndef CLOTH_PLANES
#define CLOTH_PLANES 0
#endif
#define ANALYTIC_ROWS (CLOTH_SPHERES + 3 * CLOTH_CYLINDERS + 4 * CLOTH_BOXES + 2 * CLOTH_PLANES)
