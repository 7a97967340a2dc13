/* collide_particle.cl: one float4 particle (w = inverse mass, 0 = pinned) through every
 * collider, for the solvers that keep float4 rows and collide once a substep's iterations are
 * done: pbd_cloth.cl and vbd_cloth.cl (and self_collision.cl's pbd_self_collision, after its
 * push, in either). Included after collide.cl and, with meshes, <mesh_colliders>; MESH_ARG is
 * body_args.cl's. */

/* collisions as position projections, free particles only: spheres, cylinders, boxes, planes,
 * then meshes (colliders: the substep's table) */
INLINE float4 collide_particle(float4 p, __constant float4 *colliders MESH_ARG)
{
    if (p.w == 0.0f)
        return p; /* pinned particles are never collided */
    float3 x = collide(p.xyz, colliders, CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_BOXES, CLOTH_PLANES);
#if CLOTH_MESHES > 0
    x = collide_meshes(x, colliders + ANALYTIC_ROWS, mesh_geometry, mesh_ints);
#endif
    return (float4)(x, p.w);
}
