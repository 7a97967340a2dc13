/* vbd_newton.h: the arithmetic of one particle's Newton step (docs/vbd.md, "One particle's
 * step") that the VBD kernels share: kernels/vbd_cloth.c, vbd_cloth.cl and vbd_cloth.cu. The
 * includer defines VBD_REAL (its working type) and VBD_FN (its inline function qualifier),
 * and may define VBD_MASK (what the solve's "every pivot > 0" is: int unless defined, an int
 * vector where VBD_REAL is a float vector, as vbd_cloth.cl's vector sweep includes it a second
 * time under other names); every operation here is one rounding, in the doc's order, and the
 * includer's strict build contracts none of them. No include guard: that second inclusion. */
#ifndef VBD_MASK
#define VBD_MASK int
#endif

/* One spring's share of the gradient f and the Hessian h (xx, yy, zz, xy, xz, yz): d = xi - xj,
 * L2 = |d|^2 > 0, s = k (1 - rest / L). The clamp is a select, not max(): k max(1 - rest/L, 0). */
VBD_FN void vbd_add_spring(VBD_REAL dx, VBD_REAL dy, VBD_REAL dz, VBD_REAL L2, VBD_REAL s, VBD_REAL k, VBD_REAL *f,
                           VBD_REAL *h)
{
    f[0] = f[0] + dx * s;
    f[1] = f[1] + dy * s;
    f[2] = f[2] + dz * s;
    const VBD_REAL a = s > 0 ? s : (VBD_REAL)0;
    const VBD_REAL bb = (k - a) / L2;
    const VBD_REAL bx = bb * dx, by = bb * dy, bz = bb * dz;
    h[0] = h[0] + (a + bx * dx);
    h[1] = h[1] + (a + by * dy);
    h[2] = h[2] + (a + bz * dz);
    h[3] = h[3] + bx * dy;
    h[4] = h[4] + bx * dz;
    h[5] = h[5] + by * dz;
}

/* H p = f by LDL^T without pivoting, in docs/vbd.md's order: (px, py, pz), and whether every
 * pivot is > 0 (always, for the positive definite H of a finite state). */
VBD_FN VBD_MASK vbd_ldlt_solve(VBD_REAL hxx, VBD_REAL hyy, VBD_REAL hzz, VBD_REAL hxy, VBD_REAL hxz, VBD_REAL hyz,
                          VBD_REAL fx, VBD_REAL fy, VBD_REAL fz, VBD_REAL *px, VBD_REAL *py, VBD_REAL *pz)
{
    const VBD_REAL l10 = hxy / hxx, l20 = hxz / hxx;
    const VBD_REAL d1 = hyy - l10 * hxy;
    const VBD_REAL t = hyz - l20 * hxy;
    const VBD_REAL l21 = t / d1;
    const VBD_REAL d2 = (hzz - l20 * hxz) - l21 * t;
    const VBD_REAL z1 = fy - l10 * fx;
    const VBD_REAL z2 = (fz - l20 * fx) - l21 * z1;
    *pz = z2 / d2;
    *py = z1 / d1 - l21 * *pz;
    *px = (fx / hxx - l10 * *py) - l20 * *pz;
    return (hxx > 0) & (d1 > 0) & (d2 > 0);
}
