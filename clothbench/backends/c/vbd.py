"""The `c` backend's VBD solver (docs/vbd.md): kernels/vbd_cloth.c, built per scene with the
Verlet kernel's flags (verlet.build_flags) and called through ctypes.

Host code only; the step is in the kernel file. The state stays in the backend's aligned
planes: the position at the start of a substep and the velocity, which the library steps in
place; upload turns (pos, prev) into that velocity and read turns it back with NumPy's own
operations (docs/vbd.md, "One step"), so the reference's bits go in and come out. Threads are
the Verlet class's kernel shape (CBackend: threads=T, tuned by measurement); they split rows
of a colour, never one particle's work, so they change no bit.

[self_collision] (docs/vbd.md, "Self-collision"): the Verlet library's pass, built in by the same
-DCLOTH_SELF and given the same numbers, exclude2 and work space (CBackend._contact_args); it
runs every substep after the sweeps, before the colliders.

Arithmetics (docs/c.md has the flags): strict is NumPy float32 (and float64) bit for bit;
fast contracts and takes one 1/sqrt per spring (tests/contract/test_vbd_contract.py holds it
within 1e-4 m of the float64 reference).
"""

from __future__ import annotations

import ctypes
from dataclasses import replace

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.native import build_library
from clothbench.model.scene import Scene
from clothbench.model.solver import Vbd
from clothbench.backends.base import Backend, BackendOptions
from clothbench.backends.c.verlet import SELF_FLAG, CBackend, aligned, build_flags, thread_count
from clothbench.model.kernel_inputs import VbdConstants, collider_rows

VBD_KERNEL_FILE = "vbd_cloth.c"

_VBD_LIBRARIES: dict[tuple[str, ...], ctypes.CDLL] = {}


def load_vbd_library(flags: tuple[str, ...]) -> ctypes.CDLL:
    """The built VBD library for `flags`, loaded once per process, its entry points typed."""
    lib = _VBD_LIBRARIES.get(flags)
    if lib is None:
        lib = build_library(VBD_KERNEL_FILE, flags)
        p, i = ctypes.c_void_p, ctypes.c_int
        lib.cloth_vbd_advance.argtypes = [p, p, p, p, p, p, p, p, i, i, i, i]
        if SELF_FLAG in flags:  # the pass's numbers, exclude2, the work space (cloth_advance's)
            lib.cloth_vbd_advance.argtypes += [p, ctypes.c_longlong, p]
            lib.cloth_contact_ints.restype = ctypes.c_int
        lib.cloth_vbd_advance.restype = None
        lib.cloth_grid.restype = lib.cloth_real_bytes.restype = ctypes.c_int
        _VBD_LIBRARIES[flags] = lib
    return lib


class CVbdBackend(CBackend):
    """VBD on the CPU: the Verlet class's threads, capabilities and tuning, its own state."""

    # the Verlet class's: its precisions, both arithmetics, thread shapes, [self_collision] (after
    # the sweeps, before the colliders: docs/vbd.md); neither meshes, motion nor boxes
    capabilities = replace(CBackend.capabilities, self_collision=(*CBackend.capabilities.self_collision, "vbd"))

    # the tuning key's "kernel" covers what vbd_cloth.c includes (verlet_cloth.c, vbd_newton.h):
    # an edit to any of them measures again; no layout field: VBD's planes are n*n apart
    kernel_file = VBD_KERNEL_FILE
    layout_key: dict[str, str] = {}

    def __init__(self, scene: Scene, solver: Vbd, options: BackendOptions):
        Backend.__init__(self, scene, solver, options)  # none of the Verlet state
        t = self.dtype = options.dtype
        self.n2 = scene.particles
        self.flags = build_flags(scene, options.precision, options.strict)
        self._lib = load_vbd_library(self.flags)
        if self._lib.cloth_grid() != scene.grid or self._lib.cloth_real_bytes() != np.dtype(t).itemsize:
            raise ClothbenchError(f"c: the cached library for {self.flags} is not the one it names; clear its cache")
        c = self._constants = VbdConstants.of(scene, solver, t)  # rounded once, docs/vbd.md
        self._numbers = np.array((c.h, c.mh2, c.bh, c.k, *c.gh2, *c.rest, *c.omega), dtype=t)
        # the table in the step's order (collider_rows' keys), never empty: a valid pointer
        self._colliders = np.concatenate([*(r.reshape(-1) for r in collider_rows(scene, t).values()), np.zeros(1, t)])
        self._chebyshev = solver.chebyshev_rho > 0  # rho = 0: no extrapolation at all, as NumPy's
        self._x, self._v, self._y, self._iterate = (aligned(3 * self.n2, t) for _ in range(4))
        self._before = aligned(2 * 3 * self.n2 if self._chebyshev else 1, t)
        self._w = aligned(self.n2, t)
        self._contact = self._contact_args(scene, t)  # [self_collision]: (numbers, exclude2, cells), or ()
        self.threads = thread_count(self.pick_shape(self._tuning_key(), self._time_shape))
        self.run_note = self._fewer_threads_if_busy()

    def _tuning_key(self) -> dict[str, str]:
        return {**super()._tuning_key(), "solver": "vbd"}

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if np.shape(pos) != expected or np.shape(prev) != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {np.shape(pos)} and {np.shape(prev)}")
        t = self.dtype
        x, xp = (np.asarray(state, t)[:, :3].T for state in (pos, prev))
        self._x[:] = x.reshape(-1)
        self._v[:] = ((x - xp) / self._constants.dt).reshape(-1)  # NumPy VBD's upload, operation for operation
        self._w[:] = np.asarray(pos, t)[:, 3]

    def advance(self, steps: int) -> None:
        if steps <= 0:
            return
        if self._x.size == 0:
            raise ClothbenchError("c: advance after close")
        contact = ()
        if self._contact:
            numbers, exclude2, cells = self._contact
            contact = (numbers.ctypes.data, exclude2, cells.ctypes.data)
        self._lib.cloth_vbd_advance(
            self._x.ctypes.data,
            self._v.ctypes.data,
            self._w.ctypes.data,
            self._y.ctypes.data,
            self._iterate.ctypes.data,
            self._before.ctypes.data,
            self._numbers.ctypes.data,
            self._colliders.ctypes.data,
            self.solver.iterations,
            int(self._chebyshev),
            int(steps) * self.solver.substeps,
            self._threads_now(),
            *contact,
        )

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        x = self._x.reshape(3, self.n2)
        prev = x - self._v.reshape(3, self.n2) * self._constants.dt  # NumPy VBD's read
        return self._rows(x), self._rows(prev)

    def _rows(self, planes: np.ndarray) -> np.ndarray:
        out = np.empty((self.n2, 4), self.dtype)
        out[:, :3] = planes.T
        out[:, 3] = self._w
        return out

    def close(self) -> None:
        self._x = np.zeros(0, self.dtype)
