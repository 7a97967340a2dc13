"""The analytic collider kinds, once: the table every reader of a kind takes it from.

Per kind, in the order the step applies them (docs/semantics.md): its scene-file table and
keys, its dataclass (colliders/analytic.py), the Scene field and collider table key that hold
it, the float4 rows a kernel takes per collider (model/kernel_inputs.py lays them out), the
name of its response function in each language that has one, and the Capabilities field
that says which backends take it where not every backend does. The scene reader, the
collider table, the kernels' counts and the refusals all read this; docs/colliders.md is the
checklist for adding a kind.
"""

from __future__ import annotations

from dataclasses import dataclass

from clothbench.model.colliders.analytic import Box, Cylinder, Plane, Sphere

# The languages a response is written in: the NumPy reference (backends/numpy/verlet.py) and
# the kernels (kernels/verlet_cloth.c, collide.cl, collide_KIND.glsl, verlet_cloth.cu).
LANGUAGES = ("numpy", "c", "opencl", "glsl", "cuda")

# How each kernel language names a kind's count: its define, or (glsl-uniform) the generic
# GL program's uniform. {NAME}/{PLURAL} are the kind's name in capitals, {plural} as it is.
COUNT_NAMES = {
    "c": "CLOTH_{PLURAL}",
    "opencl": "CLOTH_{PLURAL}",
    "glsl": "{NAME}_COUNT",
    "glsl-uniform": "num_{plural}",
    "cuda": "CLOTH_{NAME}_COUNT",
}


@dataclass(frozen=True)
class ColliderKind:
    name: str  # its [[name]] table in a scene file, and its dataclass's `kind`
    plural: str  # the Scene field holding them, and collider_rows' key
    type: type  # its dataclass, in colliders/analytic.py
    keys: tuple[str, ...]  # the keys its table needs
    rows: int  # float4 rows per collider (kernel_inputs.collider_rows)
    numbers: tuple[str, ...] = ()  # keys that are one number; every other key is three
    optional: tuple[str, ...] = ()  # its own optional keys, beside COLLIDER_OPTIONAL_KEYS
    # the languages (LANGUAGES) with a response for it: its function there is collide_NAME
    languages: tuple[str, ...] = LANGUAGES
    # the Capabilities field naming the solvers for which a backend takes it; None: every
    # backend takes it, with every solver
    capability: str | None = None

    @property
    def response(self) -> str:
        """Its response function's name, the same in every language that has one."""
        return f"collide_{self.name}"

    def function(self, language: str) -> str | None:
        """The name of its response function in `language`, or None where it has none yet."""
        return self.response if language in self.languages else None

    def count_name(self, language: str) -> str:
        """The name `language`'s kernel takes its count by (COUNT_NAMES)."""
        return COUNT_NAMES[language].format(NAME=self.name.upper(), PLURAL=self.plural.upper(), plural=self.plural)


# The kinds in the order the step applies them (after them, the meshes): boxes before planes,
# so that a floor plane still acts last.
KINDS = (
    ColliderKind("sphere", "spheres", Sphere, keys=("center", "radius"), numbers=("radius",), rows=1),
    ColliderKind("cylinder", "cylinders", Cylinder, keys=("start", "end", "radius"), numbers=("radius",), rows=3),
    ColliderKind("box", "boxes", Box, keys=("center", "half_extents"), optional=("rotation",), rows=4, capability="boxes"),
    ColliderKind("plane", "planes", Plane, keys=("point", "normal"), rows=2),
)  # fmt: skip
KIND = {k.name: k for k in KINDS}


def kinds_in(language: str) -> tuple[ColliderKind, ...]:
    """The kinds `language` has a response for, in the step's order."""
    return tuple(k for k in KINDS if language in k.languages)
