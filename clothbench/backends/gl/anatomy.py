"""Where a GL step's time goes: the step's shader with parts of it cut out, each timed alone.

`python -m clothbench.backends.gl.anatomy [--grid N] [--reps R]` builds the strict
glsl-compute interior pass and the strict glsl fragment draw of the sphere scene, then
variants of each with one more part removed (the square roots and divisions, the spring
arithmetic, the neighbour loads, the whole step, the input loads), and prints the milliseconds
(wall and process CPU) per dispatch or draw, the best of 5 rounds of R back-to-back calls.
The differences between rows are what each part costs (docs/llvmpipe.md). The variants
compute wrong physics on purpose: this is a measuring tool, never a backend. Set
LP_NUM_THREADS before running it to fix llvmpipe's thread count.
"""

from __future__ import annotations

import argparse
import os
import re
import time

from clothbench.errors import ClothbenchError
from clothbench.model.scene import load_scene, load_setup
from clothbench.backends.base import BackendOptions

ROUNDS = 5

# (label, pattern, replacement) applied cumulatively to the strict source, in this order
_SPRING_HEAD = r"vec3 spring\(vec3 x, vec3 xj, vec3 bv, float rest_o\)\n\{"
_COMMON_CUTS = [
    ("without sqrt and division (f = d - bv)", r"P vec3 f = s \* d - bv;", "P vec3 f = d - bv;"),
    ("without spring arithmetic (f = neighbour)", _SPRING_HEAD, r"\g<0> return xj;"),
    ("without the 12 neighbour loads", r"for \(int o = 0; o < 12; \+\+o\)", "for (int o = 0; o < 0; ++o)"),
]
COMPUTE_CUTS = _COMMON_CUTS + [
    ("copy: no step at all", re.escape("vec4 x_new = vec4(verlet(rc, x, xp, self.w), self.w);"), "vec4 x_new = self;"),
    (
        "stores only (constants)",
        r"void main\(\)\n\{",
        r"\g<0> { ivec2 r0 = particle(); if (r0.x < 0) return; int i0 = r0.x * n + r0.y;"
        r" prev[i0] = vec4(1.0); return; }",
    ),
    ("empty dispatch", r"void main\(\)\n\{", r"\g<0> return;"),
]
FRAGMENT_CUTS = _COMMON_CUTS + [
    ("copy: no step at all", re.escape("pos_out = vec4(verlet(rc, x, xp, self.w), self.w);"), "pos_out = self;"),
    ("stores only (constants)", r"void main\(\)\n\{", r"\g<0> pos_out = vec4(1.0); prev_out = vec4(2.0); return;"),
]


def variants(source: str, cuts) -> list[tuple[str, str]]:
    """(label, source) of the full shader and of each cumulative cut; a cut whose pattern is
    not in the source is an error (it would time the previous variant again)."""
    out = [("full strict step", source)]
    for label, pattern, replacement in cuts:
        if not re.search(pattern, source):
            raise ClothbenchError(f"anatomy: the kernel changed, {label!r} finds nothing to cut")
        source = re.sub(pattern, replacement, source, count=1)
        out.append((label, source))
    return out


def _best(call, finish, reps: int) -> tuple[float, float]:
    """(wall ms, CPU ms) per call: the best of ROUNDS rounds of `reps` calls."""
    for _ in range(3):
        call()
    finish()
    wall = cpu = float("inf")
    for _ in range(ROUNDS):
        c, t = time.process_time(), time.perf_counter()
        for _ in range(reps):
            call()
        finish()
        wall = min(wall, (time.perf_counter() - t) / reps * 1e3)
        cpu = min(cpu, (time.process_time() - c) / reps * 1e3)
    return wall, cpu


def compute_rows(n: int, reps: int) -> list[tuple[str, float, float]]:
    from clothbench.backends.gl.compute import GLSLComputeBackend, PASS_INTERIOR

    setup = load_setup("sphere")
    backend = GLSLComputeBackend(
        load_scene("sphere").replace(grid=n), setup.solver, BackendOptions(strict=True, shape="wg=64")
    )
    rows = []
    with backend, backend.gl:
        backend.upload(*backend.initial_state())
        groups = backend.plan.passes[0][1]
        ctx = backend.gl.ctx
        for label, source in variants(backend.sources[(PASS_INTERIOR, "wg=64")], COMPUTE_CUTS):
            program = ctx.compute_shader(source)
            backend._bind_state(image_reads=backend.image_reads)

            def call(program=program):
                program.run(*groups)
                ctx.memory_barrier()

            rows.append((f"glsl-compute interior pass: {label}", *_best(call, ctx.finish, reps)))
            program.release()
    return rows


def fragment_rows(n: int, reps: int) -> list[tuple[str, float, float]]:
    from clothbench.backends.gl import context as gl_context
    from clothbench.backends.gl.fragment import GLSLBackend

    setup = load_setup("sphere")
    backend = GLSLBackend(load_scene("sphere").replace(grid=n), setup.solver, BackendOptions(strict=True))
    if not backend.image_reads:
        raise ClothbenchError("anatomy: the fragment variants need imageLoad (GL 4.2)")
    rows = []
    vertex = gl_context.shader_source("verlet_cloth.vert", backend.gl.version_code, {})
    with backend, backend.gl:
        backend.upload(*backend.initial_state())
        ctx = backend.gl.ctx
        ctx.disable(ctx.BLEND | ctx.DEPTH_TEST | ctx.CULL_FACE)
        for label, source in variants(backend.source, FRAGMENT_CUTS):
            program = ctx.program(vertex_shader=vertex, fragment_shader=source)
            vao = ctx.vertex_array(program, [])
            backend.textures[0][0].bind_to_image(0, read=True, write=False)
            backend.textures[0][1].bind_to_image(1, read=True, write=False)
            backend.fbos[1].use()

            def call(vao=vao):
                vao.render(mode=ctx.TRIANGLES, vertices=3)

            rows.append((f"glsl draw: {label}", *_best(call, ctx.finish, reps)))
            vao.release()
            program.release()
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m clothbench.backends.gl.anatomy", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--grid", type=int, default=256)
    parser.add_argument("--reps", type=int, default=40, help="calls per timed round")
    args = parser.parse_args(argv)
    if args.grid < 5 or args.reps < 1:
        parser.error("--grid must be >= 5 and --reps >= 1")
    try:
        rows = compute_rows(args.grid, args.reps) + fragment_rows(args.grid, args.reps)
    except ClothbenchError as e:
        print(f"anatomy: error: {e}")
        return 2
    threads = os.environ.get("LP_NUM_THREADS", "default")
    print(f"n = {args.grid}, LP_NUM_THREADS={threads}; ms per call, best of {ROUNDS} rounds of {args.reps}")
    for label, wall, cpu in rows:
        print(f"{label:68s} wall {wall:8.4f}  cpu {cpu:8.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
