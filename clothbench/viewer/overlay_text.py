"""What the viewer's overlay says: the run (top left), the profiler (top right, P), the last
event and the keys (bottom left)."""

from __future__ import annotations

from clothbench.viewer.draw import DIM, WARN, wrap
from clothbench.viewer.keys import backend_key_span, help_lines, key_of
from clothbench.viewer.session import has_stages

WIDTH = 58  # characters of the run panel's widest line
PROFILER_WIDTH = 44
HINT = "H keys  {} backend  1-5 grid  S C G colliders  R reset  space pause  N step  W wire  P profiler  E f64 error"


def _ms(value) -> str:
    return f"{value:.2f} ms" if value is not None else "-"


def run_lines(viewer, profile) -> list:
    s = viewer.session
    scene, solver, b = s.scene, s.solver, s.backend
    n = scene.grid
    lines = [
        f"{scene.name}  {solver.spec}  {n}x{n}: {scene.particles:,} particles, {scene.springs:,} springs",
        f"backend   {key_of(s.backend_name)} {s.backend_name}  {b.mode}",
        f"device    {_cut(b.device, WIDTH - 10)}",
    ]
    step_ms = profile.step_ms
    per_step = f"  {step_ms / s.steps_per_frame:.3f} ms/step" if not s.paused else ""
    lines.append(f"physics   {step_ms:.2f} ms/frame  avg {_ms(viewer.avg_step_ms)}{per_step}")
    fps = f"{viewer.fps:.1f}" if viewer.fps else "-"
    last = viewer.last_tree.ms if viewer.last_tree is not None else None
    lines.append(f"fps       {fps}  (frame {_ms(last)})")
    lines.append(f"dt        {solver.dt * 1e3:g} ms  iterations {s.steps_per_frame} steps/frame")
    if solver.name == "pbd":
        lines.append(f"pbd       {solver.method}: {solver.iterations} iterations x {solver.substeps} substeps")
    if solver.name == "vbd":
        lines.append(f"vbd       {solver.iterations} sweeps x {solver.substeps} substeps")
    lines.append(f"step      {s.step:,} = {s.step * solver.dt:.3f} s simulated" + ("  PAUSED" * s.paused))
    if viewer.source == "device":
        where = "textures" if s.backend_name == "glsl" else "storage buffers"
        lines.append(f"drawn     from device memory: {s.backend_name}'s {where}")
        lines.append("          in the window's GL context, no readback")
    else:
        lines.append("drawn     from a readback: state -> host -> GL")
        lines.append("          buffer, every frame")
    if s.shadow is not None:
        if s.error is None:
            lines.append(f"error     vs float64 NumPy from step {s.shadow_since:,}")
        else:
            rms, worst = s.error
            lines.append(f"error     vs float64 NumPy since step {s.shadow_since:,}:")
            lines.append(f"          RMS {rms:.2e} m, max {worst:.2e} m")
    colliders = [f"{k} {len(getattr(scene, k))}" for k in ("spheres", "cylinders", "planes") if getattr(scene, k)]
    lines.append("colliders " + (", ".join(colliders) or "none") + ("   wireframe" if viewer.wireframe else ""))
    if s.options.strict and b.options.strict and b.flushes_subnormals:
        lines.append(("note      this driver flushes subnormal floats:", WARN))
        lines.append(("          strict holds while none occurs", WARN))
    return lines


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 3] + "..."


def profiler_lines(viewer) -> list:
    tree = viewer.last_tree
    if tree is None:
        return ["profiler: from the next frame"]
    lines = [(f"{'profiler, frame ' + str(viewer.frame - 1):<18}{'time':>11} {'parent':>6} {'frame':>6}", DIM)]
    lines += tree.lines(tree.ms)
    lines += [(line, DIM) for line in wrap(viewer.timer_note, PROFILER_WIDTH)]
    if viewer.session.profiling and viewer.session.backend_name:
        if has_stages(viewer.session.backend):
            note = "kernel stages: the backend's profile_stages, synchronised between stages"
            lines += [(line, DIM) for line in wrap(note, PROFILER_WIDTH)]
    return lines


def panels(viewer, profile) -> list:
    out = [("top-left", run_lines(viewer, profile))]
    if viewer.show_profiler:
        out.append(("top-right", profiler_lines(viewer)))
    bottom = []
    if viewer.session.message:
        bottom.append((viewer.session.message, WARN))
    if viewer.show_help:
        bottom += [f"{key:<11} {what}" for key, what in help_lines()]
    else:
        bottom.append((HINT.format(backend_key_span()), DIM))
    out.append(("bottom-left", bottom))
    return out
