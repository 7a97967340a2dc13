"""The plan of variants: which backend runs with which options and which solver. Every
command that runs many backends (sweep, accuracy, stability, the hard cases) takes its
variants from plan_variants, so the skip rules and the names are the same everywhere."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterable

from clothbench.backends import BACKENDS, BackendOptions, availability, backend_class
from clothbench.errors import ClothbenchError
from clothbench.solver import Solver, Verlet

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
        return self.capabilities.mode(self.options, self.solver)

    @property
    def name(self) -> str:
        """'backend mode', a PBD one with its iterations (and substeps when more than one):
        'numpy f32/pbd-jacobi/10it'."""
        if self.solver.name != "pbd":
            return f"{self.backend} {self.mode}"
        sub = f"x{self.solver.substeps}" if self.solver.substeps > 1 else ""
        return f"{self.backend} {self.mode}/{self.solver.iterations}it{sub}"

    @property
    def is_reference(self) -> bool:
        """The numpy float64 run: its final state is every other row's reference."""
        return self.backend == "numpy" and self.options.precision == "f64" and self.options.local_size is None


def variant_label(overrides: dict, options: BackendOptions) -> str:
    """A mode name from a variant's option overrides, e.g. 'strict per-step' or 'f64'."""
    parts = []
    for k, v in overrides.items():
        if isinstance(v, bool):
            parts.append(k if v else ("fast" if k == "strict" else f"no-{k}"))
        elif v is not None:
            parts.append(str(v))
    if options.generic and "generic" not in overrides:
        parts.append("generic")
    return " ".join(parts) or "default"


def plan_variants(
    names: Iterable[str],
    solvers: Iterable[Solver] = (Verlet(),),
    base: BackendOptions = BackendOptions(),
    local_sizes: Iterable[int] = (),
    generic: str = "no",
) -> tuple[list[Variant], list[tuple[str, str]]]:
    """Every usable backend in `names` × solver × its declared sweep variants (× local sizes
    where it has a work-group size; × specialised and generic kernels with generic="both",
    the generic one right after its specialised twin), the float64 reference first per
    solver; and (name, reason) for each backend that cannot run here (said once) or has no
    class for a solver ('name (pbd)')."""
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
                skipped.append((f"{name} ({solver.name})", f"cannot load its {solver.name} class: {type(e).__name__}: {e}"))
                continue
            adapted = caps.adapt(base)
            sizes = (None, *local_sizes) if caps.local_size else (None,)
            for overrides in caps.sweep_variants:
                v = replace(adapted, **overrides)
                own_size = "local_size" in overrides  # a variant that fixes its size keeps it
                for ls in sizes:
                    for g in kernels if caps.generic else (v.generic,):
                        o = replace(v if own_size else replace(v, local_size=ls), generic=g)
                        in_solver.setdefault((name, o), Variant(name, o, solver, variant_label(overrides, o)))
        variants += sorted(in_solver.values(), key=lambda v: not v.is_reference)  # stable: reference first
    # a backend without a solver is said once even when several solvers of that kind are asked for
    return variants, list(dict.fromkeys(skipped))
