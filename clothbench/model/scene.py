"""The scene: what is simulated (static, validated, immutable) and its initial state.

A scene never changes during a run; the changing part is the state, two (n*n, 4) arrays
`pos` and `prev` whose w component is the particle's inverse mass (0 = pinned).
The step semantics are in docs/semantics.md; this module only holds the data.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from clothbench.model.colliders.analytic import (
    COLLIDER_OPTIONAL_KEYS,
    Box,
    Cylinder,
    Plane,
    Sphere,
    body_pose,  # noqa: F401 (re-exported)
)
from clothbench.model.colliders.kinds import KINDS, ColliderKind
from clothbench.model.colliders.mesh import Mesh
from clothbench.model.colliders.motion import (
    Frame,
    Motion,
    array_of_tables,
    finite3,
    frames_from_toml,
    motion_from_toml,
    refuse_unknown_keys,
)
from clothbench.model.colliders.self_contact import SelfCollision, self_collision_from_toml
from clothbench.errors import SceneError
from clothbench.model.solver import (
    FLOAT32_MAX,
    FLOAT32_TINY,
    SOLVERS,
    Pbd,
    Solver,
    Vbd,
    Verlet,
    finite_number,
    solver_for_spec,
)

# The 12-spring stencil as (d_row, d_col), in the order every backend sums it.
STRUCTURAL = ((0, -1), (0, 1), (-1, 0), (1, 0))
SHEAR = ((-1, -1), (-1, 1), (1, -1), (1, 1))
BEND = ((-2, -2), (-2, 2), (2, -2), (2, 2))
OFFSETS = STRUCTURAL + SHEAR + BEND
# the kind of spring of each offset (0 structural, 1 shear, 2 bend), in OFFSETS order:
# every kernel takes one rest length (and PBD one compliance) per kind and picks it by this
OFFSET_KIND = tuple(kind for kind, group in enumerate((STRUCTURAL, SHEAR, BEND)) for _ in group)
# rest length of each offset in units of the grid spacing h
OFFSET_LENGTH = tuple(math.hypot(dr, dc) for dr, dc in OFFSETS)

CORNERS = ("top-left", "top-right", "bottom-left", "bottom-right")
EDGES = ("top", "bottom", "left", "right")

# Keys the scene file may use, per table: anything else is a typo and is refused.
_CLOTH_KEYS = {"grid", "size", "height", "mass", "stiffness", "damping"}
_SIM_KEYS = {"dt", "steps", "gravity", "start", "solver"}
_PBD_KEYS = {"method", "iterations", "substeps", "relaxation", "compliance", "chebyshev_rho"}
_VBD_KEYS = {"iterations", "substeps", "chebyshev_rho"}
_PIN_KEYS = {"indices", "corners", "edge", "attach"}
_MESH_KEYS = {"file", "shape", "subdivisions", "position", "rotation", "scale", "margin", *COLLIDER_OPTIONAL_KEYS}
_TABLES = {
    "name",
    "description",
    "cloth",
    "sim",
    "pbd",
    "vbd",
    "pins",
    *(k.name for k in KINDS),
    "mesh",
    "frame",
    "self_collision",
}


@dataclass(frozen=True)
class PinGroup:
    """One table of a [[pins]] array: its particles (as [pins] names them) and the body they
    follow (None: fixed where they start)."""

    indices: tuple[int, ...] = ()
    corners: tuple[str, ...] = ()
    edge: str | None = None
    attach: str | None = None


@dataclass(frozen=True)
class Scene:
    """The model: what is simulated, apart from how it is stepped (solver.py) and for how
    long. Validated on construction."""

    name: str = "custom"
    description: str = ""
    # [cloth]
    grid: int = 64  # n: particles per side
    size: float = 1.0  # side length of the sheet (m)
    height: float = 1.0  # y of the flat initial sheet (m)
    mass: float = 0.01  # mass of one particle (kg)
    stiffness: float = 1000.0  # k of every spring (N/m)
    damping: float = 0.002  # b of every spring (N s/m), applied to the particle's own velocity
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)  # [sim] gravity (m/s^2)
    # colliders (one field per kind of colliders/kinds.py, its `plural`) and pins
    spheres: tuple[Sphere, ...] = ()
    cylinders: tuple[Cylinder, ...] = ()
    boxes: tuple[Box, ...] = ()
    planes: tuple[Plane, ...] = ()
    pin_indices: tuple[int, ...] = ()
    pin_corners: tuple[str, ...] = ()
    pin_edge: str | None = None
    # triangle meshes (applied after the planes), kinematic frames, and the body the pins follow
    meshes: tuple[Mesh, ...] = ()
    frames: tuple[Frame, ...] = ()
    pin_attach: str | None = None
    # [[pins]]: several pinned sets, each following its own body (kernel_inputs.pin_targets);
    # then pin_attach is the first group's body that attaches, and None stops every group
    pin_groups: tuple[PinGroup, ...] = ()
    # [self_collision] (docs/semantics.md, "Self-collision"); None: no pass, nothing compiled in
    self_collision: SelfCollision | None = None

    def __post_init__(self):
        _validate(self)

    # --- derived, never stored -------------------------------------------------
    @property
    def particles(self) -> int:
        return self.grid * self.grid

    @property
    def spacing(self) -> float:
        return self.size / (self.grid - 1)

    @property
    def springs(self) -> int:
        return count_springs(self.grid)

    @property
    def colliders(self) -> tuple:
        """The analytic colliders in the order the step applies them (colliders/kinds.py:
        spheres, cylinders, boxes, planes; the meshes come after them: `meshes`)."""
        return tuple(c for kind in KINDS for c in getattr(self, kind.plural))

    @property
    def has_motion(self) -> bool:
        """Whether a collider moves or the pins follow a body (per-step constants)."""
        return self.pin_attach is not None or any(c.motion is not None for c in self.colliders + self.meshes)

    def body(self, name: str):
        """The collider or kinematic frame called `name`."""
        for b in self.colliders + self.meshes + self.frames:
            if b.name == name:
                return b
        raise SceneError(f"no collider or frame named {name!r}")

    def rest_lengths(self) -> tuple[float, ...]:
        """Rest length of each stencil offset, |(dr, dc)| * h, in float64."""
        h = self.spacing
        return tuple(length * h for length in OFFSET_LENGTH)

    def pinned(self) -> np.ndarray:
        """Sorted indices of the pinned particles ([pins] and every [[pins]] group)."""
        idx = set().union(*(self.pinned_by(g) for g in self.pin_sets()))
        return np.array(sorted(idx), dtype=np.int64)

    def pin_sets(self) -> tuple[PinGroup, ...]:
        """The pinned sets with the body each follows: [pins] (following pin_attach) first,
        then the [[pins]] groups."""
        first = PinGroup(self.pin_indices, self.pin_corners, self.pin_edge, self.pin_attach)
        return (first, *self.pin_groups)

    def pinned_by(self, group: PinGroup) -> set[int]:
        """The particles one pinned set names."""
        n = self.grid
        idx = set(group.indices)
        corner_index = {
            "top-left": 0,
            "top-right": n - 1,
            "bottom-left": (n - 1) * n,
            "bottom-right": n * n - 1,
        }
        idx.update(corner_index[c] for c in group.corners)
        if group.edge == "top":
            idx.update(range(0, n))
        elif group.edge == "bottom":
            idx.update(range((n - 1) * n, n * n))
        elif group.edge == "left":
            idx.update(range(0, n * n, n))
        elif group.edge == "right":
            idx.update(range(n - 1, n * n, n))
        return idx

    def replace(self, **changes) -> "Scene":
        """A copy with some values changed, validated again."""
        return dataclasses.replace(self, **changes)

    def initial_state(self, dtype=np.float64, shift=None) -> tuple[np.ndarray, np.ndarray]:
        """(pos, prev) as (n*n, 4) arrays of `dtype`: a flat sheet at rest, computed in float64
        and rounded once. `shift` (x, y, z), a solver's start (Stepping.initial_state): a free
        particle's prev is its position plus shift, added in float64 before the rounding.

        Only the two result arrays are written, from float64 rows and columns of the sheet (x
        depends on the column alone, z on the row): at 2048^2 whole-sheet float64 temporaries
        made a fresh process's first start 3.6 s (the solver's shift 13 s), this 0.5."""
        n, h = self.grid, self.spacing
        along = np.arange(n) * h  # float64: col * h and row * h
        pinned = self.pinned()
        pos, prev = np.empty((n * n, 4), dtype=dtype), np.empty((n * n, 4), dtype=dtype)
        for out, (sx, sy, sz) in ((pos, (0.0, 0.0, 0.0)), (prev, shift or (0.0, 0.0, 0.0))):
            grid = out.reshape(n, n, 4)
            grid[:, :, 0] = (along + sx)[None, :]
            grid[:, :, 1] = self.height + sy
            grid[:, :, 2] = (along + sz)[:, None]
            out[:, 3] = 1.0 / self.mass
            out[pinned, 3] = 0.0
        prev[pinned] = pos[pinned]  # a pin does not move: no shift
        return pos, prev


def count_springs(n: int) -> int:
    """Springs counted per particle (each spring seen from both ends), as the chapter counts."""
    return sum(max(0, n - abs(dr)) * max(0, n - abs(dc)) for dr, dc in OFFSETS)


def _validate(s: Scene) -> None:
    if not isinstance(s.grid, int) or isinstance(s.grid, bool) or s.grid < 3:
        raise SceneError(f"grid must be an integer >= 3, got {s.grid!r}")
    for name, positive in (
        ("size", True),
        ("mass", True),
        ("stiffness", False),
        ("damping", False),
        ("height", None),
    ):
        value = getattr(s, name)
        if not finite_number(value):
            raise SceneError(f"{name} must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise SceneError(f"{name} must be > 0, got {value!r}")
        if positive is False and value < 0:
            raise SceneError(f"{name} must be >= 0, got {value!r}")
    object.__setattr__(s, "gravity", finite3(s.gravity, "gravity"))
    for collider in s.colliders:
        collider.check()
    _check_float32_range(s)
    n2 = s.grid * s.grid
    for group in s.pin_sets():
        for i in group.indices:
            if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < n2:
                raise SceneError(f"pin index {i!r} is outside the grid (0 .. {n2 - 1})")
        for c in group.corners:
            if c not in CORNERS:
                raise SceneError(f"unknown pin corner {c!r} (known: {', '.join(CORNERS)})")
        if group.edge is not None and group.edge not in EDGES:
            raise SceneError(f"unknown pin edge {group.edge!r} (known: {', '.join(EDGES)})")
    seen: set[int] = set()
    for group in s.pin_sets():
        both = seen & s.pinned_by(group)
        if both:
            raise SceneError(f"particle {min(both)} is pinned by two [[pins]] tables: each pins its own particles")
        seen |= s.pinned_by(group)
    _validate_bodies(s)
    if s.self_collision is not None and not isinstance(s.self_collision, SelfCollision):
        raise SceneError(f"self_collision must be a SelfCollision or None, got {s.self_collision!r}")


def _validate_bodies(s: Scene) -> None:
    """Meshes (loaded once here), names, motions and the body the pins follow."""
    for mesh in s.meshes:
        mesh.check()
        for what, v in (("position", max(map(abs, mesh.position))), ("margin", mesh.margin)):
            if v > FLOAT32_MAX:
                raise SceneError(f"mesh {what} {v!r} is too large for float32 (max {FLOAT32_MAX:.4g})")
    names = [b.name for b in s.colliders + s.meshes + s.frames if b.name]
    for name in names:
        if not isinstance(name, str) or names.count(name) > 1:
            raise SceneError(f"collider or frame name {name!r} is used more than once")
    for k, group in enumerate(s.pin_sets()):
        if group.attach is None:
            continue
        if group.attach not in names:
            raise SceneError(
                f"pins attach to {group.attach!r}, which names no collider or frame "
                f"(named: {', '.join(names) or 'none'})"
            )
        gate_only = k == 0 and s.pin_groups  # with [[pins]], pin_attach only says whether the pins follow
        if not (group.indices or group.corners or group.edge) and not gate_only:
            raise SceneError("[pins] attach needs pinned particles (indices, corners or edge)")


def _check_float32_range(s: Scene) -> None:
    """Every backend but the f64 reference works in float32: a value it cannot hold is
    refused here rather than becoming inf inside a kernel."""
    values = {name: getattr(s, name) for name in ("size", "height", "mass", "stiffness", "damping")}
    values["gravity"] = max(map(abs, s.gravity))
    for c in s.colliders:
        for f in dataclasses.fields(c):
            v = getattr(c, f.name)
            if f.name in COLLIDER_OPTIONAL_KEYS:
                continue  # a name, and a motion (an overflowing pose shows as a blow-up)
            values[f"{c.kind} {f.name}"] = max(map(abs, v)) if isinstance(v, tuple) else v
    for name, value in values.items():
        if abs(value) > FLOAT32_MAX:
            raise SceneError(f"{name} {value!r} is too large for float32 (max {FLOAT32_MAX:.4g})")
        if value != 0 and abs(value) < FLOAT32_TINY:
            raise SceneError(
                f"{name} {value!r} is too small for float32 (it would be 0 or lose its precision; "
                f"smallest normal {FLOAT32_TINY:.4g})"
            )


def check_float32_step(scene: Scene, solver: Solver) -> None:
    """The products a float32 step forms from the scene's constants and dt: refused when
    one overflows (inf inside the kernel) or a nonzero one underflows to 0."""
    dt2 = solver.dt * solver.dt
    terms = {
        "stiffness * dt^2 / mass": scene.stiffness * dt2 / scene.mass if scene.mass else 0.0,
        "damping * dt / mass": scene.damping * solver.dt / scene.mass if scene.mass else 0.0,
        "gravity * dt^2": max(map(abs, scene.gravity)) * dt2,
    }
    for name, value in terms.items():
        if not math.isfinite(value) or abs(value) > FLOAT32_MAX:
            raise SceneError(
                f"{name} = {value:.3g} overflows float32 (max {FLOAT32_MAX:.4g}): use a smaller dt or constant"
            )
        if value != 0 and abs(value) < FLOAT32_TINY:
            raise SceneError(
                f"{name} = {value:.3g} underflows float32 (smallest normal {FLOAT32_TINY:.4g}): "
                "the float32 step would lose it; use a larger dt or constant"
            )


# --- TOML -------------------------------------------------------------------------


def _table(data: dict, key: str, allowed: set, where: str) -> dict:
    table = data.get(key, {})
    if not isinstance(table, dict):
        raise SceneError(f"{where}: [{key}] must be a table")
    refuse_unknown_keys(table, allowed, where, f"[{key}]")
    return table


def _colliders(data: dict, kind: ColliderKind, where: str) -> tuple:
    """The [[kind]] array of tables as collider objects, every key checked."""
    keys, optional_keys = kind.keys, kind.optional + COLLIDER_OPTIONAL_KEYS
    out = []
    for table in array_of_tables(data.get(kind.name, []), kind.name, "colliders", where):
        optional = _optional_keys(table, kind.name, where)
        unknown = set(table) - set(keys) - set(optional_keys)
        missing = set(keys) - set(table)
        if unknown or missing:
            raise SceneError(
                f"{where}: [[{kind.name}]] needs {', '.join(keys)} (optional: {', '.join(optional_keys)})"
                + (f" (unknown: {sorted(unknown)[0]!r})" if unknown else "")
                + (f" (missing: {sorted(missing)[0]!r})" if missing else "")
            )
        values = {
            k: table[k] if k in kind.numbers else finite3(table[k], f"{kind.name} {k}")
            for k in keys + kind.optional
            if k in table
        }
        out.append(kind.type(**values, **optional))
    return tuple(out)


def _optional_keys(table: dict, kind: str, where: str) -> dict:
    """A collider's name and motion, checked."""
    out = {}
    if "name" in table:
        if not isinstance(table["name"], str) or not table["name"]:
            raise SceneError(f"{where}: [[{kind}]] name must be a non-empty string, got {table['name']!r}")
        out["name"] = table["name"]
    if "motion" in table:
        out["motion"] = motion_from_toml(table["motion"], f"{where}: [[{kind}]]")
    return out


def _meshes(data: dict, where: str, folder: Path | None) -> tuple:
    """The [[mesh]] tables; a relative file is read from the scene file's folder."""
    out = []
    for table in array_of_tables(data.get("mesh", []), "mesh", "meshes", where):
        refuse_unknown_keys(table, _MESH_KEYS, where, "[[mesh]]")
        values = _optional_keys(table, "mesh", where)
        if "file" in table:
            if not isinstance(table["file"], str):
                raise SceneError(f"{where}: [[mesh]] file must be a path, got {table['file']!r}")
            path = Path(table["file"])
            values["file"] = str(path if path.is_absolute() or folder is None else folder / path)
        if "shape" in table:
            values["shape"] = table["shape"]
        for k in ("position", "rotation"):
            if k in table:
                values[k] = finite3(table[k], f"mesh {k}")
        if "scale" in table:
            scale = table["scale"]
            values["scale"] = (
                (float(scale),) * 3 if finite_number(scale) else finite3(scale, "mesh scale (one number or three)")
            )
        for k in ("subdivisions", "margin"):
            if k in table:
                values[k] = table[k]
        out.append(Mesh(**values))
    return tuple(out)


def _pins(data: dict, where: str) -> tuple[dict, tuple[PinGroup, ...]]:
    """[pins] as today's table, or [[pins]] (several tables) as groups, each following its own
    body; then the table returned holds only the first attaching group's body (the gate)."""
    if not isinstance(data.get("pins"), list):
        return _table(data, "pins", _PIN_KEYS, where), ()
    groups = []
    for table in array_of_tables(data["pins"], "pins", "pinned sets", where):
        pins = _table({"pins": table}, "pins", _PIN_KEYS, where)
        indices, corners = pins.get("indices", []), pins.get("corners", [])
        if not isinstance(indices, list) or not isinstance(corners, list):
            raise SceneError(f"{where}: [[pins]] indices and corners must be lists")
        groups.append(PinGroup(tuple(indices), tuple(corners), pins.get("edge"), pins.get("attach")))
    attached = [g.attach for g in groups if g.attach is not None]
    return ({"attach": attached[0]} if attached else {}), tuple(groups)


@dataclass(frozen=True)
class Setup:
    """What a scene file describes: the model, the solver that steps it, the run length, and
    the file's [pbd] and [vbd] settings (kept whatever the solver is, for commands that switch)."""

    scene: Scene
    solver: Solver
    steps: int = 300
    pbd: Pbd = Pbd()
    vbd: Vbd = Vbd()

    def __post_init__(self):
        if not isinstance(self.steps, int) or isinstance(self.steps, bool) or self.steps < 1:
            raise SceneError(f"steps must be an integer >= 1, got {self.steps!r}")
        if isinstance(self.solver, Pbd):
            self.solver.compliance_for(self.scene)  # refuses stiffness 0 without a compliance
        check_float32_step(self.scene, self.solver)

    def solver_for(self, spec: str) -> Solver:
        """The solver a --solvers entry names, with this file's dt, start and [pbd] or [vbd] settings."""
        return solver_for_spec(spec, self.solver, self.pbd, self.vbd)

    def replace(
        self,
        grid=None,
        steps=None,
        dt=None,
        solver=None,
        method=None,
        iterations=None,
        substeps=None,
        chebyshev_rho=None,
    ):
        """A copy with command-line overrides applied (None: keep), validated again."""
        given = dict(method=method, iterations=iterations, substeps=substeps, chebyshev_rho=chebyshev_rho)
        pbd_changes = {k: v for k, v in given.items() if v is not None}
        pbd = self.pbd.replace(**pbd_changes)
        vbd_changes = {k: v for k, v in pbd_changes.items() if k != "method"}  # a method is PBD's
        vbd = self.vbd.replace(**vbd_changes)
        current = self.solver.replace(**({"dt": dt} if dt is not None else {}))
        if isinstance(current, Pbd):
            current = current.replace(**pbd_changes)
        elif isinstance(current, Vbd):
            current = current.replace(**vbd_changes)
        if solver is not None and solver != current.name:
            current = solver_for_spec(solver, current, pbd, vbd)
        return Setup(
            self.scene.replace(grid=grid) if grid is not None else self.scene,
            current,
            steps if steps is not None else self.steps,
            pbd.replace(dt=current.dt, start=current.start),
            vbd.replace(dt=current.dt, start=current.start),
        )


def setup_from_dict(data: dict, where: str = "scene", folder: Path | None = None) -> Setup:
    refuse_unknown_keys(data, _TABLES, where, what="table or key")
    cloth = _table(data, "cloth", _CLOTH_KEYS, where)
    sim = dict(_table(data, "sim", _SIM_KEYS, where))
    pins, pin_groups = _pins(data, where)
    pbd = _table(data, "pbd", _PBD_KEYS, where)
    vbd = _table(data, "vbd", _VBD_KEYS, where)
    colliders = {kind.plural: _colliders(data, kind, where) for kind in KINDS}
    meshes = _meshes(data, where, folder)
    frames = frames_from_toml(data.get("frame", []), where)
    self_collision = self_collision_from_toml(data.get("self_collision"), where)
    scene_kwargs = dict(cloth)
    if "gravity" in sim:
        scene_kwargs["gravity"] = finite3(sim.pop("gravity"), "gravity")
    indices = pins.get("indices", [])
    corners = pins.get("corners", [])
    if not isinstance(indices, list) or not isinstance(corners, list):
        raise SceneError(f"{where}: [pins] indices and corners must be lists")
    solver_name = sim.pop("solver", "verlet")
    steps = sim.pop("steps", 300)
    try:
        if solver_name not in SOLVERS:
            raise SceneError(f"solver must be one of {', '.join(SOLVERS)}, got {solver_name!r}")
        scene = Scene(
            name=str(data.get("name", "custom")),
            description=str(data.get("description", "")),
            **colliders,
            pin_indices=tuple(indices),
            pin_corners=tuple(corners),
            pin_edge=pins.get("edge"),
            **({"meshes": meshes} if meshes else {}),
            **({"frames": frames} if frames else {}),
            **({"pin_attach": pins["attach"]} if "attach" in pins else {}),
            **({"pin_groups": pin_groups} if pin_groups else {}),
            **({"self_collision": self_collision} if self_collision else {}),
            **scene_kwargs,
        )
        pbd_settings = Pbd(**sim, **pbd)  # sim now holds dt and start only
        vbd_settings = Vbd(**sim, **vbd)
        solver = {"pbd": pbd_settings, "vbd": vbd_settings}.get(solver_name) or Verlet(**sim)
        return Setup(scene, solver, steps, pbd_settings, vbd_settings)
    except SceneError as e:
        raise SceneError(f"{where}: {e}") from None


def builtin_scenes() -> list[str]:
    folder = resources.files("clothbench") / "scenes"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_scene(name_or_path: str) -> Scene:
    """The model of a built-in scene or scene file (load_setup: with its solver and steps)."""
    return load_setup(name_or_path).scene


def load_setup(name_or_path: str) -> Setup:
    """A built-in scene by name (`sphere`, `drape`, ...) or a TOML file by path: the model,
    its solver settings and run length."""
    path = Path(name_or_path)
    folder = resources.files("clothbench") / "scenes"  # a built-in scene's meshes ship beside it
    if name_or_path.endswith(".toml") or path.exists():
        where = str(path)
        folder = path.parent
        try:
            text = path.read_text(encoding="utf-8")
        except IsADirectoryError:
            raise SceneError(f"scene file {where} is a directory, expected a .toml file") from None
        except UnicodeDecodeError as e:
            raise SceneError(f"scene file {where} is not UTF-8 text (byte {e.start}): expected a .toml file") from None
        except OSError as e:
            raise SceneError(f"cannot read scene file {where}: {e.strerror}") from None
    else:
        if name_or_path not in builtin_scenes():
            raise SceneError(
                f"unknown scene {name_or_path!r} (built in: {', '.join(builtin_scenes())}; or give a .toml file)"
            )
        where = f"built-in scene {name_or_path}"
        text = (resources.files("clothbench") / "scenes" / f"{name_or_path}.toml").read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{where}: not valid TOML: {e}") from None
    data.setdefault("name", path.stem if where == str(path) else name_or_path)
    return setup_from_dict(data, where, Path(str(folder)))


__all__ = [
    "Scene",
    "Setup",
    "Sphere",
    "Cylinder",
    "Box",
    "Plane",
    "Mesh",
    "Frame",
    "Motion",
    "PinGroup",
    "SelfCollision",
    "OFFSETS",
    "count_springs",
    "load_scene",
    "load_setup",
    "builtin_scenes",
]
