"""The interface every backend implements, and the options a run may pass to it.

A backend owns the device state of one scene. The harness drives it:
upload the initial state once, advance k steps (the state stays on the device),
synchronise before reading the clock, read back only when asked, close.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from ..scene import Scene


@dataclass(frozen=True)
class BackendOptions:
    """Run options. A backend uses the ones that apply to it and ignores the rest."""

    precision: str = "f32"  # "f32" everywhere; "f64" only on numpy (the reference)
    strict: bool = False  # bit-exact with the numpy f32 reference: no contraction, no fast math
    transfer: str | None = None  # opencl: resident|per-step; cuda: swap|copy (None = default)
    local_size: int | None = None  # work-group / block size (None = let the runtime choose)
    device: str | None = None  # device selector where a backend has several
    gl: str = "egl"  # GL context provider for the GL backends: egl|osmesa
    normals: bool = False  # compute normals (rendering, --save-normals)
    generic: bool = False  # one kernel for every scene instead of a specialised one

    @property
    def dtype(self):
        return np.float64 if self.precision == "f64" else np.float32


@dataclass(frozen=True)
class Availability:
    """Whether a backend can run here; if not, why (one line a person can act on)."""

    usable: bool
    reason: str = ""
    device: str = ""


class Backend(ABC):
    """One simulation on one device. Subclasses supply the device-specific parts only."""

    name: str = "?"
    # Option overrides a sweep measures for this backend by default, one CSV row each,
    # e.g. ({"strict": True}, {"strict": False}) or transfer modes.
    sweep_variants: tuple[dict, ...] = ({},)
    # Whether options.local_size means something here (work-group / block size).
    has_local_size: bool = False
    # Whether options.generic selects a different kernel (one for every scene) from the
    # default one specialised for the scene.
    has_generic: bool = False

    def __init__(self, scene: Scene, options: BackendOptions):
        self.scene = scene
        self.options = options

    @property
    @abstractmethod
    def device(self) -> str:
        """What the work runs on, as the driver names it."""

    @property
    def mode(self) -> str:
        """The settings that change speed or results, for tables and CSV rows."""
        return "strict" if self.options.strict else "fast"

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
