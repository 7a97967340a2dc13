/* collide.cl: the colliders of docs/semantics.md ("Collisions"), operation for operation, on
 * one float3 position, for the kernels that take float4 positions: verlet_cloth.cl (its
 * generic build) and pbd_cloth.cl include it (the host resolves the #include:
 * clothbench/kernel_source.py resolve_includes).
 *
 * The including file defines dot3(a, b) first: (a.x*b.x + a.y*b.y) + a.z*b.z wherever the
 * result must be exact (not dot(): its order is the driver's).
 *
 * The collider table (one __constant float4 array, rows rounded once from float64 on the
 * host, clothbench/backends/kernel_inputs.py collider_rows): spheres (centre, radius); then
 * cylinders, three rows each: (start, length), (unit axis, radius), (radial_r, 0); then boxes,
 * four rows each: (centre, 0), (axis i, half extent i) for i = 0, 1, 2; then planes, two rows
 * each: (point, 0), (unit normal, 0).
 */

/* Push a point inside a sphere (centre xyz, radius w) out to its surface. */
float3 collide_sphere(float3 x, float4 sphere)
{
    float3 c = sphere.xyz;
    float r = sphere.w;
    float3 d = x - c;
    float L2 = dot3(d, d);
    float L = sqrt(L2);
    if (L < r)
        x = L2 > 0.0f ? c + d * (r / L)
                      : (float3)(c.x, c.y + r, c.z); /* exactly at the centre: straight up */
    return x;
}

/* Push a point inside a capped cylinder out the shortest way: the side or the nearer cap. */
float3 collide_cylinder(float3 x, float4 start_len, float4 axis_r, float4 radial_r)
{
    float3 a = start_len.xyz, u = axis_r.xyz;
    float len = start_len.w, r = axis_r.w;
    float3 d = x - a;
    float t = dot3(d, u); /* axial coordinate from the start cap */
    float3 q = u * t;
    float3 p = d - q; /* radial vector */
    float rho2 = dot3(p, p);
    float rho = sqrt(rho2);
    if (t > 0.0f && t < len && rho < r) {
        float side = r - rho, to_end = len - t;
        if (side <= t && side <= to_end) /* through the curved side */
            x = rho2 > 0.0f ? (a + q) + p * (r / rho)
                            : (a + q) + radial_r.xyz; /* on the axis: a fixed direction */
        else if (t <= to_end) /* through the start cap */
            x = x - q;
        else /* through the end cap */
            x = x + u * to_end;
    }
    return x;
}

/* Push a point strictly inside an oriented box (centre; unit axes with their half extents in w)
 * out through the face of least penetration, on the point's side (ties: the lower axis). */
float3 collide_box(float3 x, float4 center, float4 ax0, float4 ax1, float4 ax2)
{
    float3 d = x - center.xyz;
    float l0 = dot3(d, ax0.xyz), l1 = dot3(d, ax1.xyz), l2 = dot3(d, ax2.xyz); /* box coordinates */
    float p0 = ax0.w - fabs(l0), p1 = ax1.w - fabs(l1), p2 = ax2.w - fabs(l2); /* depth per face pair */
    if (p0 > 0.0f && p1 > 0.0f && p2 > 0.0f) {
        float3 axis = ax0.xyz;
        float l = l0, h = ax0.w, p = p0;
        if (p1 < p) {
            axis = ax1.xyz;
            l = l1;
            h = ax1.w;
            p = p1;
        }
        if (p2 < p) {
            axis = ax2.xyz;
            l = l2;
            h = ax2.w;
        }
        float s = l >= 0.0f ? h : -h; /* the face on the point's side (+ at l == 0) */
        x = x + axis * (s - l);
    }
    return x;
}

/* Push a point below a one-sided plane (point, unit normal) back onto it. */
float3 collide_plane(float3 x, float4 point, float4 normal)
{
    float3 nrm = normal.xyz;
    float dist = dot3(x - point.xyz, nrm);
    if (dist < 0.0f)
        x = x - nrm * dist;
    return x;
}

/* Every collider of the table, in the order docs/semantics.md fixes: spheres, cylinders,
 * boxes, planes. The counts are arguments (generic) or build constants (folded by the
 * compiler). */
float3 collide(float3 x, __constant float4 *colliders, int num_spheres, int num_cylinders,
               int num_boxes, int num_planes)
{
    for (int s = 0; s < num_spheres; ++s)
        x = collide_sphere(x, colliders[s]);
    __constant float4 *cylinders = colliders + num_spheres;
    for (int c = 0; c < num_cylinders; ++c)
        x = collide_cylinder(x, cylinders[3 * c], cylinders[3 * c + 1], cylinders[3 * c + 2]);
    __constant float4 *boxes = cylinders + 3 * num_cylinders;
    for (int b = 0; b < num_boxes; ++b)
        x = collide_box(x, boxes[4 * b], boxes[4 * b + 1], boxes[4 * b + 2], boxes[4 * b + 3]);
    __constant float4 *planes = boxes + 4 * num_boxes;
    for (int p = 0; p < num_planes; ++p)
        x = collide_plane(x, planes[2 * p], planes[2 * p + 1]);
    return x;
}
