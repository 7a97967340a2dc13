"""A variant's names, spelled and read back in one place: its mode (the CSV's mode column,
every table and legend), its name ('backend mode', with a PBD or VBD run's iterations), its model key
(the converged reference it is measured against), and the command-line flags that run it.

Every writer spells through here and every reader parses through here, so a name cannot
drift between the two: tests/test_variant_names.py holds parse(spell(v)) == v and
spell(parse(s)) == s for every variant the plan produces.

A mode is its option words, in this order, then what the run adds after them:

    precision  where the backend has several (f32, f64)
    strict|fast  where the backend has both (Capabilities.strict)
    pbd-METHOD  a PBD run
    vbd        a VBD run
    normals, generic  where asked for
    transfer   where the backend has transfer modes (its default named too)
    ls=N|auto  where the backend has a work-group size
    ...        the kernel shape that ran (v8/wg=64, threads=4), mesh=ALGORITHM, a backend's
               own suffix (osmesa, ssbo-reads, no-fma, compiled): kept as written

and 'default' where no option word applies (the rest still follows it).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

from clothbench.model.solver import Solver

# the choices of an option, once: the CLI's argparse choices, the backends' checks and the
# help read these
PRECISIONS = ("f32", "f64")  # f32 everywhere; f64 where a backend declares it (numpy: the reference)
GL_PROVIDERS = ("egl", "osmesa")  # the GL context a GL backend opens (headless EGL, or OSMesa)
# every backend's transfer modes (how its Verlet state moves between host and device; the
# first is its default): its Capabilities.transfers reads them here, as the mode's parser does
TRANSFERS = {"opencl": ("resident", "per-step"), "cuda": ("swap", "copy")}
PER_STEP_TRANSFERS = frozenset({"per-step"})  # those that move the state host<->device every step

SEPARATOR = "/"
DEFAULT = "default"  # the mode's head where no option word applies
VBD = "vbd"  # the mode's word for a VBD run (solver.Vbd.name)
AUTO = "auto"  # ls=auto: the runtime chooses the work-group size
_ALL_TRANSFERS = frozenset(t for modes in TRANSFERS.values() for t in modes)
_ITERATIONS = re.compile(r"^(\d+)it(?:x(\d+))?$")


def transfers_help(after_name: str = ": ", between: str = "; ") -> str:
    """'opencl: resident|per-step; cuda: swap|copy', for a help text or a column's doc."""
    return between.join(f"{backend}{after_name}{'|'.join(modes)}" for backend, modes in TRANSFERS.items())


@dataclass(frozen=True)
class Mode:
    """A mode's words, each None (or False) where the mode does not name it."""

    precision: str | None = None
    strict: bool | None = None  # None: the backend has one mode
    pbd: str | None = None  # the PBD solver's spec ('pbd-jacobi'); None: Verlet or VBD
    vbd: bool = False  # a VBD run
    normals: bool = False
    generic: bool = False
    transfer: str | None = None
    local_size: int | str | None = None  # an int, AUTO, or None where the backend has no size
    rest: tuple[str, ...] = field(default=())  # what the run adds: shape, mesh=, suffix

    def spell(self) -> str:
        head = []
        if self.precision is not None:
            head.append(self.precision)
        if self.strict is not None:
            head.append("strict" if self.strict else "fast")
        if self.pbd is not None:
            head.append(self.pbd)
        if self.vbd:
            head.append(VBD)
        head += ["normals"] * self.normals + ["generic"] * self.generic
        if self.transfer is not None:
            head.append(self.transfer)
        if self.local_size is not None:
            head.append(f"ls={self.local_size}")
        return SEPARATOR.join([SEPARATOR.join(head) or DEFAULT, *self.rest])

    @classmethod
    def parse(cls, text: str) -> Mode:
        """The words of a mode as spell() writes them; what follows the option words is rest."""
        words = text.split(SEPARATOR)
        found: dict = {}

        def take(name: str, matches, value) -> None:
            if words and matches(words[0]):
                found[name] = value(words.pop(0))

        if words[0] == DEFAULT:
            words.pop(0)
        else:
            take("precision", lambda w: w in PRECISIONS, str)
            take("strict", lambda w: w in ("strict", "fast"), lambda w: w == "strict")
            take("pbd", lambda w: w.startswith("pbd-"), str)
            take("vbd", lambda w: w == VBD, bool)
            take("normals", lambda w: w == "normals", bool)
            take("generic", lambda w: w == "generic", bool)
            take("transfer", lambda w: w in _ALL_TRANSFERS, str)
            take("local_size", lambda w: w.startswith("ls="), _local_size)
        return cls(**found, rest=tuple(words))

    def base(self) -> Mode:
        """The mode without the kernel shape tuned for the grid: its work-group size and what
        follows it, or the rest from a c shape (threads=T) on. A sweep's rows of one variant
        then share a line whatever shape won on each grid."""
        if self.local_size is not None:
            return replace(self, local_size=None, rest=())
        cut = next((i for i, w in enumerate(self.rest) if w.startswith("threads=")), len(self.rest))
        return replace(self, rest=self.rest[:cut])


def _local_size(word: str) -> int | str:
    size = word.removeprefix("ls=")
    return AUTO if size == AUTO else int(size)


def base_mode(mode: str) -> str:
    """'fast/resident' of 'fast/resident/ls=32/rows/v16/wg=32' (Mode.base)."""
    return Mode.parse(mode).base().spell()


def mesh_word(algorithm: str) -> str:
    """The mode's word for a mesh algorithm: 'mesh=accelerated'."""
    return f"mesh={algorithm}"


def iterations_word(iterations: int, substeps: int = 1) -> str:
    """A PBD or VBD run's iterations (and substeps when more than one): '10it', '10itx2'."""
    return f"{iterations}it" + (f"x{substeps}" if substeps > 1 else "")


@dataclass(frozen=True)
class VariantName:
    """'backend mode', a PBD or VBD one with its iterations: 'numpy f32/pbd-jacobi/10it'."""

    backend: str
    mode: Mode
    iterations: int | None = None  # PBD and VBD only
    substeps: int = 1

    def spell(self) -> str:
        words = [self.mode.spell()] + [iterations_word(self.iterations, self.substeps)] * (self.iterations is not None)
        return f"{self.backend} {SEPARATOR.join(words)}"

    @classmethod
    def parse(cls, text: str) -> VariantName:
        backend, _, mode = text.partition(" ")
        parsed = Mode.parse(mode)
        m = _ITERATIONS.match(parsed.rest[-1]) if (parsed.pbd or parsed.vbd) and parsed.rest else None
        if m is None:
            return cls(backend, parsed)
        return cls(backend, replace(parsed, rest=parsed.rest[:-1]), int(m[1]), int(m[2] or 1))


def variant_name(backend: str, mode: Mode, solver: Solver) -> str:
    """The name of `backend` run in `mode` by `solver` (VariantName)."""
    iterative = solver.name != "verlet"
    return VariantName(
        backend, mode, solver.iterations if iterative else None, solver.substeps if iterative else 1
    ).spell()


def solver_model(spec: str, iterations: int | None = None, substeps: int = 1) -> str:
    """A solver model without its constants: 'verlet', 'pbd-jacobi/10it', 'vbd/10it'."""
    if not spec.startswith(("pbd", VBD)):
        return "verlet"
    return f"{spec}{SEPARATOR}{iterations_word(iterations, substeps)}"


def model_name(solver: Solver) -> str:
    """The model a converged reference is of: 'verlet', 'pbd-jacobi/10it, relaxation 1.5', or
    'vbd/10it' (with ', chebyshev_rho R' where it extrapolates)."""
    if solver.name == VBD:
        rho = f", chebyshev_rho {solver.chebyshev_rho:g}" if solver.chebyshev_rho > 0 else ""
        return f"{solver_model(solver.spec, solver.iterations, solver.substeps)}{rho}"
    if solver.name != "pbd":
        return solver_model(solver.name)
    relax = f", relaxation {solver.relaxation:g}" if solver.method == "jacobi" else ""
    comp = "" if solver.compliance is None else f", compliance {list(solver.compliance)}"
    return f"{solver_model(solver.spec, solver.iterations, solver.substeps)}{relax}{comp}"


def model_short(model: str) -> str:
    """'pbd-jacobi/10it' of 'pbd-jacobi/10it, relaxation 1.5': the model without its constants."""
    return model.split(",")[0]


def iterations_display(iterations) -> str:
    """A PBD or VBD run's iterations as tables name them: '10 it'."""
    return f"{iterations} it"


def model_display(solver: str, pbd_method: str | None, iterations=None) -> str:
    """A model as tables and legends name it: 'Verlet', 'PBD jacobi', 'PBD jacobi, 10 it',
    'VBD', 'VBD, 10 it'."""
    if solver == VBD:
        return f"VBD, {iterations_display(iterations)}" if iterations is not None else "VBD"
    if solver != "pbd":
        return "Verlet"
    text = f"PBD {pbd_method or ''}".rstrip()
    return f"{text}, {iterations_display(iterations)}" if iterations is not None else text


def variant_label(overrides: dict, options) -> str:
    """A variant's label from its option overrides (Capabilities.sweep_variants) and its
    options (a BackendOptions), e.g. 'strict per-step' or 'f64': its mode until measured."""
    parts = []
    for k, v in overrides.items():
        if isinstance(v, bool):
            parts.append(k if v else ("fast" if k == "strict" else f"no-{k}"))
        elif v is not None:
            parts.append(str(v))
    if options.generic and "generic" not in overrides:
        parts.append("generic")
    if options.mesh_collision:
        parts.append(mesh_word(options.mesh_collision))
    return " ".join(parts) or DEFAULT


def option_flags(options) -> list[str]:
    """The command-line flags that give `options` (a BackendOptions), none for a default:
    the inverse of cli/args.options_from_args."""
    default = type(options)()
    flags = []
    if options.precision != default.precision:
        flags += ["--precision", options.precision]
    if options.strict:
        flags.append("--strict")
    for flag, value in (
        ("--transfer", options.transfer),
        ("--local-size", options.local_size),
        ("--device", options.device),
    ):
        if value is not None:
            flags += [flag, str(value)]
    if options.gl != default.gl:
        flags += ["--gl", options.gl]
    if options.normals:
        flags.append("--save-normals")
    if options.generic:
        flags.append("--generic")
    if options.shape is not None:
        flags += ["--shape", options.shape]
    if options.retune:
        flags.append("--retune")
    if options.mesh_collision is not None:
        flags += ["--mesh-collision", options.mesh_collision]
    return flags
