"""Every hard case runs on every backend the registry knows, once per sweep variant (mode).

A backend that cannot run here contributes one test that skips with the registry's reason
(tests/conftest.py require()), so the skip list says what was not compared and why.
A test module uses it with `from hard_case_variants import variant`.
"""

from __future__ import annotations

import pytest

from clothbench.backends import BACKENDS, availability
from clothbench.harness.plan import plan_variants

from conftest import require  # tests/conftest.py

__all__ = ["require", "variant", "run_from", "exact_arithmetic"]


def _params():
    params = []
    for name in BACKENDS:
        if not availability(name).usable:
            params.append(pytest.param((name, None), id=name))
            continue
        # the hard cases test clothbench's own kernels' edge semantics in the quick tier; the
        # peers, whose contract the quick tier runs, meet them in the full tier
        marks = pytest.mark.full if BACKENDS[name].peer else ()
        for v in plan_variants([name])[0]:
            tag = v.label.replace(" ", "-")
            params.append(pytest.param((name, v), id=f"{name}-{tag}" if tag != "default" else name, marks=marks))
    return params


@pytest.fixture(params=_params())
def variant(request):
    """A usable Variant (backend + options), or a skip with the reason it cannot run."""
    name, v = request.param
    require(name)
    return v


def run_from(v, scene, start, steps, solver=None):
    """(pos, prev) after `steps` steps of `scene` on variant `v` (stepped by `solver`, default
    the variant's) from the float64 state `start` (rounded once to the variant's precision,
    as initial_state does)."""
    from clothbench.backends import create_backend

    dtype = v.options.dtype
    with create_backend(v.backend, scene, solver or v.solver, v.options) as b:
        b.upload(start[0].astype(dtype), start[1].astype(dtype))
        b.advance(steps)
        return b.read()


def exact_arithmetic(v) -> bool:
    """Whether the variant promises the NumPy operation order (numpy itself, or --strict)."""
    return v.backend == "numpy" or v.options.strict
