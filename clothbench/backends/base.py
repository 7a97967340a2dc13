"""The interface every backend implements, what each declares it can do, and the options a
run may pass to it.

A backend owns the device state of one scene stepped by one solver. The harness drives it:
upload the initial state once, advance k steps (the state stays on the device),
synchronise before reading the clock, read back only when asked, close.

What a backend can do is declared once, as `capabilities` on its class; the registry checks
the options against it before a backend is built (one wording for every refusal), the sweep
plans its variants from it, and `Backend.mode` names a run from it (one spelling:
clothbench/variant_names.py).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, replace

import numpy as np

from clothbench.colliders.kinds import KINDS
from clothbench.errors import ClothbenchError
from clothbench.scene import Scene
from clothbench.solver import Solver
from clothbench.variant_names import AUTO, GL_PROVIDERS, PRECISIONS, SEPARATOR, Mode, mesh_word

# how a kernel finds a particle's closest mesh triangle (docs/semantics.md, "Triangle mesh"):
# every triangle in index order, or a host-built BVH traversed in the kernel; same bits
MESH_COLLISIONS = ("naive", "accelerated")


@dataclass(frozen=True)
class BackendOptions:
    """Run options. Each is checked against the backend's Capabilities before it is built."""

    precision: str = PRECISIONS[0]  # PRECISIONS: f32 everywhere, f64 where Capabilities.precisions has it
    strict: bool = False  # bit-exact with the numpy f32 reference: no contraction, no fast math
    transfer: str | None = None  # one of Capabilities.transfers (variant_names.TRANSFERS); None = default
    local_size: int | None = None  # work-group / block size (None = let the runtime choose)
    device: str | None = None  # device selector where a backend has several
    gl: str = GL_PROVIDERS[0]  # GL context provider for the GL backends (GL_PROVIDERS)
    normals: bool = False  # compute normals (rendering, --save-normals)
    generic: bool = False  # one kernel for every scene instead of a specialised one
    shape: str | None = None  # kernel shape by name (backends/tuning.py); None = the tuned one
    retune: bool = False  # measure the kernel shapes again instead of reading the cached choice
    mesh_collision: str | None = None  # naive|accelerated (MESH_COLLISIONS); None = the backend's first

    @property
    def dtype(self):
        return np.float64 if self.precision == "f64" else np.float32


@dataclass(frozen=True)
class Capabilities:
    """What one backend class can do, declared once."""

    precisions: tuple[str, ...] = PRECISIONS[:1]
    strict: bool = True  # has a strict (bit-exact) and a fast mode; False: one mode, always exact
    transfers: tuple[str, ...] = ()  # transfer modes; the first is the default
    local_size: bool = False  # options.local_size means a work-group / block size
    generic: bool = False  # options.generic selects one kernel for every scene
    normals: bool = False  # computes normals in the step (read_normals)
    device: bool = False  # options.device selects among several devices
    gl: bool = False  # options.gl selects the GL context provider
    shapes: bool = False  # has kernel shapes chosen by measurement (options.shape, options.retune)
    # scene features beyond fixed spheres, cylinders and planes (docs/semantics.md), as the
    # solvers (names) for which the backend takes them: triangle meshes, motion (moving
    # colliders, pins attached to a body), and each collider kind whose `capability` names
    # one of these fields (colliders/kinds.py); a scene that needs one is refused in one line
    # where absent. By solver because one Capabilities may serve a backend's Verlet and PBD
    # classes alike.
    meshes: tuple[str, ...] = ()
    moving_colliders: tuple[str, ...] = ()
    boxes: tuple[str, ...] = ()
    self_collision: tuple[str, ...] = ()  # the [self_collision] pass (docs/semantics.md, "Self-collision")
    # the mesh algorithms (MESH_COLLISIONS) it implements, the first its default
    mesh_collisions: tuple[str, ...] = ()
    # option overrides a sweep measures by default, one CSV row each
    sweep_variants: tuple[dict, ...] = ({},)

    def refusal(self, backend: str, options: BackendOptions) -> str | None:
        """Why `backend` cannot take `options`, in one wording, or None."""

        def no(option: str, value, takes: str) -> str:
            given = f"{option} {value}" if value != "" else option
            return f"{backend} does not take {given} (it takes: {takes})"

        if options.precision not in self.precisions:
            from clothbench.backends import precision_backends

            runs = ", ".join(precision_backends(options.precision)) or "no backend"
            return no(
                "--precision", options.precision, f"{', '.join(self.precisions)}; {options.precision} runs on: {runs}"
            )
        if options.transfer is not None and options.transfer not in self.transfers:
            return no("--transfer", options.transfer, ", ".join(self.transfers) or "no transfer modes")
        if options.local_size is not None:
            if not self.local_size:
                return no("--local-size", options.local_size, "no work-group size")
            if options.local_size < 1:
                return no("--local-size", options.local_size, "an integer >= 1")
        if options.generic and not self.generic:
            return no("--generic", "", "its scene-specialised kernel only")
        if options.normals and not self.normals:
            return no("--save-normals", "", "no normals: it does not compute them")
        if options.device is not None and not self.device:
            return no("--device", options.device, "its one device")
        if options.gl not in GL_PROVIDERS:
            return no("--gl", options.gl, ", ".join(GL_PROVIDERS))
        if options.gl != GL_PROVIDERS[0] and not self.gl:
            return no("--gl", options.gl, "no GL context")
        if options.shape is not None and not self.shapes:
            return no("--shape", options.shape, "one kernel shape")
        if options.retune and not self.shapes:
            return no("--retune", "", "one kernel shape: there is nothing to tune")
        if options.mesh_collision is not None and options.mesh_collision not in self.mesh_collisions:
            return no(
                "--mesh-collision", options.mesh_collision, ", ".join(self.mesh_collisions) or "no mesh colliders"
            )
        return None

    def scene_refusal(self, backend: str, scene: Scene, solver: str = "verlet") -> str | None:
        """Why `backend` cannot simulate `scene` with `solver` (a collider kind or motion it
        lacks), or None."""
        who = backend if solver == "verlet" else f"{backend} {solver}"
        for kind in KINDS:
            if getattr(scene, kind.plural) and kind not in self.collider_kinds(solver):
                takers = ", ".join(_declaring(kind.capability, solver)) or "no backend yet"
                return f"{who} does not take {kind.name} colliders (they run on: {takers})"
        if scene.meshes and solver not in self.meshes:
            kinds = ", ".join(kind.name for kind in self.collider_kinds(solver))
            return f"{who} does not take mesh colliders yet (it takes: {kinds}; {_takers('meshes', solver)})"
        if scene.has_motion and solver not in self.moving_colliders:
            what = (
                "moving colliders"
                if any(c.motion for c in scene.colliders + scene.meshes)
                else "pins attached to a body"
            )
            return f"{who} does not take {what} yet (it takes: fixed colliders and fixed pins; {_takers('moving_colliders', solver)})"
        if scene.self_collision is not None and solver not in self.self_collision:
            return f"{who} does not take [self_collision] yet ({_takers('self_collision', solver)})"
        return None

    def collider_kinds(self, solver: str = "verlet") -> tuple:
        """The collider kinds (colliders/kinds.py) it takes with `solver`, in the step's order."""
        return tuple(k for k in KINDS if k.capability is None or solver in getattr(self, k.capability))

    def adapt(self, options: BackendOptions) -> BackendOptions:
        """`options` less what this backend does not take: how one set of command-line
        options is given to every backend of a sweep."""
        return replace(
            options,
            precision=options.precision if options.precision in self.precisions else self.precisions[0],
            strict=options.strict and self.strict,
            transfer=options.transfer if options.transfer in self.transfers else None,
            local_size=options.local_size if self.local_size else None,
            generic=options.generic and self.generic,
            normals=options.normals and self.normals,
            device=options.device if self.device else None,
            gl=options.gl if self.gl else GL_PROVIDERS[0],
            shape=options.shape if self.shapes else None,
            retune=options.retune and self.shapes,
            mesh_collision=options.mesh_collision if options.mesh_collision in self.mesh_collisions else None,
        )

    def mode_words(self, options: BackendOptions, solver: Solver, local_size: int | None = None) -> Mode:
        """The settings that change speed or results, one spelling for every backend
        (variant_names.Mode): precision (where there are several), strict|fast, pbd-method,
        normals, generic, transfer, ls=work-group size."""
        return Mode(
            precision=options.precision if len(self.precisions) > 1 else None,
            strict=options.strict if self.strict else None,
            pbd=solver.spec if solver.name == "pbd" else None,
            normals=options.normals,
            generic=options.generic,
            transfer=(options.transfer or self.transfers[0]) if self.transfers else None,
            local_size=(local_size or options.local_size or AUTO) if self.local_size else None,
        )


def _takers(feature: str, solver: str) -> str:
    """'numpy does' (the backends that declare `feature` for `solver`), for a refusal."""
    names = _declaring(feature, solver)
    return f"{', '.join(names)} {'does' if len(names) == 1 else 'do'}" if names else "none does yet"


def _declaring(feature: str, solver: str) -> list[str]:
    """The backends whose Capabilities declare `feature` for `solver`, in the registry's order."""
    from clothbench.backends import BACKENDS, backend_class

    names = []
    for name, entry in BACKENDS.items():
        if getattr(entry, solver, None) is None:
            continue
        try:
            if solver in getattr(backend_class(name, solver).capabilities, feature):
                names.append(name)
        except Exception:  # a backend whose module cannot load here takes nothing here
            continue
    return names


@dataclass(frozen=True)
class Availability:
    """Whether a backend can run here; if not, why (one line a person can act on)."""

    usable: bool
    reason: str = ""
    device: str = ""
    # the driver (runtime, GL renderer, compiler) and its version that will run the work, as
    # Backend.driver says it: "Intel(R) Xeon(R) Processor" alone does not say which of three
    # OpenCL runtimes it is; '' where the backend names none
    driver: str = ""


class Backend(ABC):
    """One simulation on one device. Subclasses supply the device-specific parts only."""

    name: str = "?"
    capabilities: Capabilities = Capabilities()

    def __init__(self, scene: Scene, solver: Solver, options: BackendOptions):
        refusal = self.capabilities.refusal(self.name, options) or self.capabilities.scene_refusal(
            self.name, scene, solver.name
        )
        if refusal:
            raise ClothbenchError(refusal)
        self.scene = scene
        self.solver = solver
        self.options = options

    @property
    @abstractmethod
    def device(self) -> str:
        """What the work runs on, as the driver names it."""

    @property
    def driver(self) -> str:
        """The driver (or compiler) and its version that ran the work, for the row's `driver`
        column: a device name alone does not say which of several runtimes ran it."""
        return ""

    @property
    def mode(self) -> str:
        """The settings that change speed or results, for tables and CSV rows."""
        shape = self.shape.split(SEPARATOR) if self.shape else []
        mesh = [mesh_word(self.mesh_collision)] if self.mesh_collision else []
        suffix = self.mode_suffix.split(SEPARATOR)[1:]
        words = self.capabilities.mode_words(self.options, self.solver, self.effective_local_size)
        return replace(words, rest=(*shape, *mesh, *suffix)).spell()

    @property
    def mesh_collision(self) -> str | None:
        """The mesh algorithm this run uses where the scene has meshes (options.mesh_collision,
        or the backend's default), else None."""
        if not self.scene.meshes or not self.capabilities.mesh_collisions:
            return None
        return self.options.mesh_collision or self.capabilities.mesh_collisions[0]

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver=None) -> tuple[str, ...]:
        """Where capabilities.shapes: the kernel shapes this backend can run `scene` with
        (names, as the mode spells them; the first is the default), chosen among by
        measurement (backends/tuning.py) unless options.shape names one; with `solver`, only
        those its settings allow (None: every shape of any settings)."""
        return ()

    def pick_shape(self, key: dict[str, str], time_candidate) -> str:
        """options.shape if given (refused in one line if not a candidate), else the tuned
        choice for `key` (backends/tuning.py). Sets and returns self.shape."""
        from clothbench.backends.tuning import choose_shape

        candidates = self.kernel_shapes(self.scene, self.options, self.solver)
        if self.options.shape is not None:
            if self.options.shape not in candidates:
                raise ClothbenchError(
                    f"{self.name} has no kernel shape {self.options.shape!r} for this scene "
                    f"(it has: {', '.join(candidates)})"
                )
            self.shape = self.options.shape
        else:
            self.shape = choose_shape(self.name, key, candidates, time_candidate, self.options.retune)
        return self.shape

    # the kernel shape that runs (backends/tuning.py), part of the mode; None: it has one
    shape: str | None = None
    # one line on how this run differs from the backend's usual choice, for the row's note and
    # run's stderr (c: fewer threads on a busy machine); '' where it does not
    run_note: str = ""

    # the work-group size the backend chose where options.local_size is None
    effective_local_size: int | None = None
    # a backend-specific part of the mode (e.g. a slower read path it fell back to), each
    # word after a "/": "/osmesa", "/eager"
    mode_suffix: str = ""
    # whether its arithmetic flushes subnormal floats to zero (NumPy keeps them): a strict
    # run there is watched against NumPy and says where they part (harness/strict_watch.py)
    flushes_subnormals: bool = False

    def initial_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The solver's start of this scene, in this backend's working precision."""
        return self.solver.initial_state(self.scene, self.options.dtype)

    @abstractmethod
    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        """Put a (n*n, 4) state on the device (also used to restart from a saved state)."""

    @abstractmethod
    def advance(self, steps: int) -> None:
        """Enqueue `steps` steps. May return before the work is done: see synchronize()."""

    def synchronize(self) -> None:
        """Block until every enqueued step has finished (before reading a clock)."""

    @abstractmethod
    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(pos, prev) as (n*n, 4) arrays of the working precision, synchronised."""

    def read_normals(self) -> np.ndarray | None:
        """(n*n, 4) normals of the last step, where the backend computed them."""
        return None

    # The device clock device_elapsed_ms() reads (harness/timing.py DEVICE_TIMERS), '' for
    # none. No default: every backend class says which, beside the code that reads it (a GL
    # backend's depends on its driver), and tests/test_registry_facts.py fails one that does not.
    device_timer: str

    @property
    def device_timer_note(self) -> str:
        """Why this run has no device time although its backend reads a device clock (a GL
        driver whose timestamps are the host's), in one line; '' otherwise."""
        return ""

    def device_elapsed_ms(self) -> float | None:
        """Device-measured time of the last advance() (profiling events), where available."""
        return None

    def profile_stages(self, steps: int) -> dict[str, float] | None:
        """Advance `steps` steps timing each stage on its own (synchronised between stages,
        so slower than advance()); ms per step for each stage, or None where a backend has
        a single stage."""
        return None

    def close(self) -> None:
        """Release device resources."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
