"""The plan of variants: which backend runs with which options and which solver. Every
command that runs many backends (sweep, accuracy, stability, the hard cases) takes its
variants from plan_variants, so the skip rules and the names are the same everywhere."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Iterable

from clothbench.backends import BACKENDS, BackendOptions, availability, backend_class
from clothbench.model.colliders.kinds import KINDS
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene, SelfCollision
from clothbench.model.solver import Solver, Verlet
from clothbench.variant_names import mesh_word, variant_label, variant_name

GENERIC_CHOICES = ("no", "yes", "both")


@dataclass(frozen=True)
class Variant:
    """One backend with complete options and one solver: a CSV row per grid, a line on a plot."""

    backend: str
    options: BackendOptions
    solver: Solver
    label: str = "default"  # the variant, named from its overrides (the mode until measured)

    @property
    def peer(self) -> bool:
        return BACKENDS[self.backend].peer

    @property
    def capabilities(self):
        return backend_class(self.backend, self.solver.name).capabilities

    @property
    def mode(self) -> str:
        """The mode the backend will report (Backend.mode), known before it is built."""
        return self.mode_words.spell()

    @property
    def mode_words(self):
        """The mode's words (variant_names.Mode): the options' and the mesh algorithm's."""
        words = self.capabilities.mode_words(self.options, self.solver)
        mesh = (mesh_word(self.options.mesh_collision),) if self.options.mesh_collision else ()
        return replace(words, rest=mesh)

    @property
    def name(self) -> str:
        """'backend mode', a PBD one with its iterations (and substeps when more than one):
        'numpy f32/pbd-jacobi/10it' (variant_names.VariantName)."""
        return variant_name(self.backend, self.mode_words, self.solver)

    @property
    def is_reference(self) -> bool:
        """The numpy float64 run: its final state is every other row's reference."""
        return self.backend == "numpy" and self.options.precision == "f64" and self.options.local_size is None


def plan_variants(
    names: Iterable[str],
    solvers: Iterable[Solver] = (Verlet(),),
    base: BackendOptions = BackendOptions(),
    local_sizes: Iterable[int] = (),
    generic: str = "no",
    scene: Scene | None = None,
    mesh_collisions: Iterable[str] = (),
) -> tuple[list[Variant], list[tuple[str, str]]]:
    """Every usable backend in `names` × solver × its declared sweep variants (× local sizes
    where it has a work-group size; × specialised and generic kernels with generic="both",
    the generic one right after its specialised twin), the float64 reference first per
    solver; and (name, reason) for each backend that cannot run here (said once) or has no
    class for a solver ('name (pbd)').

    With `scene`: a backend that refuses it (a mesh or a motion it does not take) is skipped
    with its refusal, and in a scene with meshes every variant names its mesh algorithm: each
    of `mesh_collisions` the backend has (one variant each; those it lacks skipped with the
    reason), or its default where none is asked."""
    if generic not in GENERIC_CHOICES:
        raise ClothbenchError(f"generic must be one of {', '.join(GENERIC_CHOICES)}, got {generic!r}")
    names, solvers, local_sizes = list(names), list(solvers), tuple(local_sizes)
    kernels = {"no": (False,), "yes": (True,), "both": (False, True)}[generic]
    variants: list[Variant] = []
    skipped: list[tuple[str, str]] = []
    for i, solver in enumerate(solvers):
        in_solver: dict[tuple, Variant] = {}
        for name in names:
            avail = availability(name)
            if not avail.usable:
                if i == 0:  # said once, not once per solver
                    skipped.append((name, avail.reason))
                continue
            if solver.name not in BACKENDS[name].solvers():
                skipped.append((f"{name} ({solver.name})", f"{name} has no {solver.name} solver"))
                continue
            try:
                caps = backend_class(name, solver.name).capabilities
            except Exception as e:  # a half-written backend module is reported, not fatal
                skipped.append(
                    (f"{name} ({solver.name})", f"cannot load its {solver.name} class: {type(e).__name__}: {e}")
                )
                continue
            who = name if solver.name == "verlet" else f"{name} ({solver.name})"
            refusal = caps.scene_refusal(name, scene, solver.name) if scene is not None else None
            if refusal:  # said once, not written as a failed row per grid
                skipped.append((who, refusal))
                continue
            algorithms: tuple = (None,)
            if scene is not None and scene.meshes and caps.mesh_collisions:
                algorithms = tuple(a for a in mesh_collisions if a in caps.mesh_collisions) or (
                    () if mesh_collisions else caps.mesh_collisions[:1]  # the backend's default, named
                )
                for a in mesh_collisions:
                    if a not in caps.mesh_collisions:
                        skipped.append((f"{who} mesh={a}", caps.refusal(name, BackendOptions(mesh_collision=a))))
            adapted = caps.adapt(base)
            sizes = (None, *local_sizes) if caps.local_size else (None,)
            for overrides in caps.sweep_variants:
                v = replace(adapted, **overrides)
                own_size = "local_size" in overrides  # a variant that fixes its size keeps it
                for algorithm in algorithms:
                    for ls in sizes:
                        for g in kernels if caps.generic else (v.generic,):
                            o = replace(v if own_size else replace(v, local_size=ls), generic=g)
                            o = replace(o, mesh_collision=algorithm or o.mesh_collision)
                            in_solver.setdefault((name, o), Variant(name, o, solver, variant_label(overrides, o)))
        variants += sorted(in_solver.values(), key=lambda v: not v.is_reference)  # stable: reference first
    # a backend without a solver is said once even when several solvers of that kind are asked for
    return variants, list(dict.fromkeys(skipped))


# --- the scene a row runs: its mesh size and its motion ------------------------------------

# triangles of each built-in shape at subdivisions 0; each level multiplies them by 4
# (colliders/mesh.py, _shape_triangles: box 12 * 4^s, icosphere 20 * 4^s, torus 256 * 4^s)
SHAPE_TRIANGLES = {"box": 12, "icosphere": 20, "torus": 256}
MAX_SUBDIVISIONS = 6  # the most Mesh.check takes
MOTION_CHOICES = ("on", "off")  # --motion: the scene as its file says, or with every motion stopped
# --self-collision: the scene with its [self_collision] pass, or the same scene without the table
SELF_COLLISION_CHOICES = ("on", "off")


def shape_triangles(shape: str, subdivisions: int) -> int:
    return SHAPE_TRIANGLES[shape] * 4**subdivisions


def subdivisions_for(shape: str, triangles: int) -> int:
    """The subdivision level whose triangle count is nearest `triangles`, by ratio (the counts
    grow fourfold per level, so 'nearest' is judged on a log scale); a tie goes to the smaller."""
    levels = range(MAX_SUBDIVISIONS + 1)
    return min(levels, key=lambda s: (abs(math.log(shape_triangles(shape, s) / triangles)), s))


def with_mesh_triangles(scene: Scene, triangles: int) -> Scene:
    """`scene` with each built-in mesh shape subdivided to the level nearest `triangles`;
    ClothbenchError (one line) for a scene without meshes or with a mesh read from a file."""
    if not scene.meshes:
        raise ClothbenchError(f"--mesh-triangles: scene {scene.name} has no [[mesh]] collider to subdivide")
    files = [m.file for m in scene.meshes if m.file is not None]
    if files:
        raise ClothbenchError(
            f"--mesh-triangles sets the subdivisions of built-in shapes ({', '.join(SHAPE_TRIANGLES)}); "
            f"scene {scene.name} reads its mesh from {files[0]}, whose triangles are the file's"
        )
    meshes = tuple(replace(m, subdivisions=subdivisions_for(m.shape, triangles)) for m in scene.meshes)
    return scene.replace(meshes=meshes)


def without_motion(scene: Scene) -> Scene:
    """`scene` with every motion stopped: each collider fixed at its placement in the file and
    attached pins fixed where they start (the cloth, colliders and step otherwise the same)."""
    if not scene.has_motion:
        raise ClothbenchError(
            f"--motion: scene {scene.name} has no moving collider and no pins attached to a body: nothing to stop"
        )

    def still(bodies):
        return tuple(replace(b, motion=None) for b in bodies)

    return scene.replace(
        **{kind.plural: still(getattr(scene, kind.plural)) for kind in KINDS},
        meshes=still(scene.meshes),
        frames=still(scene.frames),
        pin_attach=None,
    )


def without_self_collision(scene: Scene) -> Scene:
    """`scene` without its [self_collision] table: the same step less the pass."""
    if scene.self_collision is None:
        raise ClothbenchError(f"--self-collision: scene {scene.name} has no [self_collision] table: nothing to time")
    return scene.replace(self_collision=None)


def mesh_triangles(scene: Scene) -> int | None:
    """Triangles of the scene's meshes as the step sees them (after the clean-up rules), or None."""
    return sum(m.geometry.triangles for m in scene.meshes) if scene.meshes else None


@dataclass(frozen=True)
class SceneVariant:
    """How a row's scene differs from the sweep's scene file: its meshes' triangle count (None:
    no meshes), its motion and its self-collision pass ('on', 'off'; '' for a scene that has none).
    `measured_with` is, for an 'off' row, the file's [self_collision] table its scene lacks: the
    end-of-run measure reads it, so that the row says how close the sheet came without the pass
    (not part of the key: the 'off' is)."""

    mesh_triangles: int | None = None
    motion: str = ""
    self_collision: str = ""
    measured_with: SelfCollision | None = field(default=None, compare=False)

    @property
    def label(self) -> str:
        parts = [f"{self.mesh_triangles} triangles"] * (self.mesh_triangles is not None)
        parts += [f"motion {self.motion}"] * bool(self.motion)
        return ", ".join(parts + [f"self-collision {self.self_collision}"] * bool(self.self_collision))


def scene_variants(
    scene: Scene, triangles: Iterable[int] = (), motion: Iterable[str] = (), self_collision: Iterable[str] = ()
) -> list[tuple[SceneVariant, Scene, list[str]]]:
    """(variant, its scene, notes) for every asked triangle count × motion × self-collision, in that order,
    duplicates (two counts nearest one level) dropped; the scene as it is when neither is asked.
    A note says where a count was moved to the nearest the shape has. Everything is checked
    before anything runs: one line for what cannot be asked of this scene."""
    triangles, motion = list(dict.fromkeys(triangles)), list(dict.fromkeys(motion))
    bad = [m for m in motion if m not in MOTION_CHOICES]
    if bad:
        raise ClothbenchError(f"--motion takes {', '.join(MOTION_CHOICES)} (comma-separated), got {bad[0]!r}")
    if motion and not scene.has_motion:
        without_motion(scene)  # raises the one-line refusal
    passes = list(dict.fromkeys(self_collision))
    bad = [p for p in passes if p not in SELF_COLLISION_CHOICES]
    if bad:
        raise ClothbenchError(
            f"--self-collision takes {', '.join(SELF_COLLISION_CHOICES)} (comma-separated), got {bad[0]!r}"
        )
    if passes:
        without_self_collision(scene)  # raises the one-line refusal for a scene without the table
    sized: list[tuple[Scene, list[str]]] = []
    for t in triangles or [None]:
        s = scene if t is None else with_mesh_triangles(scene, t)
        have = mesh_triangles(s)
        moved = t not in (None, have)
        notes = [f"--mesh-triangles {t}: {have} triangles, the nearest {_shapes(s)} has"] if moved else []
        sized.append((s, notes))
    out: dict[SceneVariant, tuple[Scene, list[str]]] = {}
    for s, notes in sized:
        for m in motion or [""]:
            moving = "on" if s.has_motion else ""
            for p in passes or [""]:
                contact = "on" if s.self_collision is not None else ""
                measured_with = s.self_collision if p == "off" else None
                key = SceneVariant(mesh_triangles(s), m or moving, p or contact, measured_with)
                run = without_motion(s) if m == "off" else s
                out.setdefault(key, (without_self_collision(run) if p == "off" else run, notes))
    return [(k, s, notes) for k, (s, notes) in out.items()]


def _shapes(scene: Scene) -> str:
    """'torus (subdivisions 1: 256*4^1)' for each mesh."""
    return " + ".join(
        f"{m.shape} (subdivisions {m.subdivisions}: {SHAPE_TRIANGLES[m.shape]}*4^{m.subdivisions})"
        for m in scene.meshes
    )
