"""The colliders as whole-array selections, for the peers written as array code over (3, n, n)
component planes (peers/torch.py, peers/jax.py): each kind's response in the NumPy
reference's operations and order (backends/numpy/verlet.py), with no data-dependent branch:
`xp.where` chooses the pushed value where a particle is inside. `xp` is the peer's array
module (torch, jax.numpy) and `sqrt` the square root its mode takes.
"""

from __future__ import annotations

from clothbench.model.scene import Scene
from clothbench.model.kernel_inputs import collider_rows
from clothbench.backends.numpy.verlet import ARGUMENTS


def dot3(a, b):
    """(a.x*b.x + a.y*b.y) + a.z*b.z, the association every kernel uses."""
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]


def _collide_sphere(x, free, xp, sqrt, c, r, top):
    d = x - c
    length2 = dot3(d, d)
    length = sqrt(length2)
    inside = (length < r) & free
    pushed = c + d * (r / length)
    pushed = xp.where(length2 == 0, top, pushed)  # exactly at the centre: straight up
    return xp.where(inside, pushed, x)


def _collide_cylinder(x, free, xp, sqrt, a, u, length, r, radial_r):
    d = x - a
    t = dot3(d, u)  # axial coordinate (m) from the start cap
    q = u * t
    p = d - q  # radial vector
    rho2 = dot3(p, p)
    rho = sqrt(rho2)
    inside = (t > 0) & (t < length) & (rho < r) & free
    # push out the shortest way: through the side, or through the nearer cap
    side = r - rho
    to_end = length - t
    through_side = (side <= t) & (side <= to_end)
    through_start = ~through_side & (t <= to_end)
    pushed_side = xp.where(rho2 == 0, (a + q) + radial_r, (a + q) + p * (r / rho))  # on the axis: radial_r
    pushed = xp.where(through_side, pushed_side, xp.where(through_start, x - q, x + u * to_end))
    return xp.where(inside, pushed, x)


def _collide_box(x, free, xp, sqrt, c, ax0, ax1, ax2, h0, h1, h2):
    d = x - c
    l0, l1, l2 = dot3(d, ax0), dot3(d, ax1), dot3(d, ax2)  # the box's own coordinates
    p0, p1, p2 = h0 - xp.abs(l0), h1 - xp.abs(l1), h2 - xp.abs(l2)  # depth through each face pair
    inside = (p0 > 0) & (p1 > 0) & (p2 > 0) & free
    # out through the face of least penetration, ties to the lower axis, on the particle's side
    take1 = p1 < p0
    take2 = p2 < xp.where(take1, p1, p0)
    lk = xp.where(take2, l2, xp.where(take1, l1, l0))
    hk = xp.where(take2, h2, xp.where(take1, h1, h0))
    axis = xp.where(take2, ax2, xp.where(take1, ax1, ax0))
    return xp.where(inside, x + axis * (xp.where(lk >= 0, hk, -hk) - lk), x)


def _collide_plane(x, free, xp, sqrt, p0, nrm):
    dist = dot3(x - p0, nrm)
    return xp.where((dist < 0) & free, x - nrm * dist, x)


COLLIDE = {"sphere": _collide_sphere, "cylinder": _collide_cylinder, "box": _collide_box, "plane": _collide_plane}


def collider_tensors(scene: Scene, tensor) -> list[tuple[str, dict]]:
    """(kind, constants) of every collider in the order the step applies them, from
    kernel_inputs.collider_rows (float32, rounded once), as `tensor` makes them."""
    rows = collider_rows(scene)

    def vec(row):
        return tensor(row[:3].reshape(3, 1, 1))

    out = []
    for s in rows["spheres"]:
        top = s[:3].copy()
        top[1] = top[1] + s[3]  # c + (0, r, 0) in float32, as the reference adds it
        out.append(("sphere", {"c": vec(s), "r": tensor(s[3]), "top": vec(top)}))
    for a, u, radial_r in rows["cylinders"].reshape(-1, 3, 4):  # (start, length), (axis, r), (radial_r, 0)
        out.append(
            (
                "cylinder",
                {"a": vec(a), "u": vec(u), "length": tensor(a[3]), "r": tensor(u[3]), "radial_r": vec(radial_r)},
            )
        )
    for block in rows["boxes"].reshape(-1, 4, 4):  # (centre, 0), (axis i, half extent i): as the reference takes them
        out.append(("box", {name: tensor(value) for name, value in ARGUMENTS["box"](*block).items()}))
    for p, nrm in rows["planes"].reshape(-1, 2, 4):
        out.append(("plane", {"p0": vec(p), "nrm": vec(nrm)}))
    return out
