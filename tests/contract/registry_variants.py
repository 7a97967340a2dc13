"""The registry as test parameters: every test in tests/contract/ runs once per backend (and
solver, and kernel build) the registry knows, with no test code of its own. A backend added
to clothbench.backends.BACKENDS gets the whole contract; one that cannot run here
contributes parameters that skip with the registry's reason (tests/conftest.py require())."""

from __future__ import annotations

import pytest

from clothbench.backends import BACKENDS, BackendOptions, availability, backend_class

from conftest import require  # tests/conftest.py

STRICT = BackendOptions(strict=True)


def backend_params(
    solver: str = "verlet", builds: bool = False, needs: str | None = None, takes: str | None = None
) -> list:
    """pytest params: each backend that implements `solver` (and, with `needs`, declares that
    capability; with `takes`, takes that scene feature for `solver`: "meshes" or
    "moving_colliders"); with `builds`, once per kernel build it declares (specialised, generic)."""
    params = []
    for name, entry in BACKENDS.items():
        if solver not in entry.solvers():
            continue
        if not availability(name).usable:
            params.append(pytest.param((name, False), id=name))  # skips with the reason
            continue
        caps = backend_class(name, solver).capabilities
        if needs is not None and not getattr(caps, needs):
            continue
        if takes is not None and solver not in getattr(caps, takes):
            continue
        generics = (False, True) if builds and caps.generic else (False,)
        for generic in generics:
            tag = "-generic" if generic else ""
            params.append(pytest.param((name, generic), id=f"{name}{tag}"))
    return params


def solver_params() -> list:
    """pytest params (backend, solver name): every solver of every backend."""
    return [
        pytest.param((name, solver), id=f"{name}-{solver}")
        for name, entry in BACKENDS.items()
        for solver in entry.solvers()
    ]


def usable(param: tuple) -> tuple:
    """The (backend, ...) parameter, or a skip saying why that backend cannot run here."""
    require(param[0])
    return param


def options(name: str, solver: str = "verlet", **values) -> BackendOptions:
    """BackendOptions with `values`, less what the backend does not take (as a sweep gives them)."""
    return backend_class(name, solver).capabilities.adapt(BackendOptions(**values))


def shapes_of(name: str, scene, solver, **values) -> tuple:
    """The kernel shapes `name` offers for `scene` and `solver` (a Pbd or a Vbd) with the options
    `values` (None: it has one, or the options fix it, as glsl-compute's --local-size does)."""
    cls = backend_class(name, solver.name)
    offered = cls.kernel_shapes(scene, options(name, solver.name, **values), solver) if cls.capabilities.shapes else ()
    return offered or (None,)
