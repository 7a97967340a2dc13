"""Drawing the cloth and its colliders offscreen with moderngl: `clothbench render`.

The cloth is the n x n sheet as indexed triangles (kernels/render_cloth.*), each grid quad
split along its (r, c)-(r+1, c+1) diagonal as in docs/normals.md, lit on both sides with the
particles' normals and patterned with a checker so folds show. The colliders are meshes
(kernels/render_collider.*): spheres, capped cylinders, boxes, a square patch of each plane, and
each [[mesh]] collider's own triangles (flat-shaded, as the step sees them); a moving one is
drawn at its pose for the frame's time (colliders/motion.py).
A frame shows x(t), the state the last step read, with its normals: what the GL kernels
compute (read()[1] of any backend).

Where the cloth comes from:
- `glsl` and `glsl-compute`: from the backend's own state textures / storage buffers
  (`drawable_state()`), as the chapter maps its render target to a vertex buffer: nothing
  leaves the device but the finished image;
- any other backend: its positions read back each frame and uploaded, with normals from
  `clothbench.harness.normals` (or the backend's own, where it computes them).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from clothbench.backends import BackendOptions, capabilities, create_backend
from clothbench.backends.gl import context as gl_context
from clothbench.reports.meshes import (
    cloth_indices,
    cube_mesh,
    cylinder_mesh,
    perpendicular,
    sphere_mesh,
    triangle_mesh,
)
from clothbench.errors import ClothbenchError
from clothbench.harness.normals import grid_normals
from clothbench.reports.render_bounds import motion_matrix, placement_matrix, scene_bounds
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver

BACKGROUND = (0.86, 0.89, 0.93)
CLOTH_COLOURS = ((0.80, 0.16, 0.13), (0.97, 0.78, 0.30))  # checker: red and gold
CHECKS = 8  # checker squares per sheet side
COLLIDER_COLOUR = (0.36, 0.52, 0.74)
FLOOR_COLOUR = (0.66, 0.66, 0.64)
# From the scene's centre toward the camera: above the sheet's first row (z = 0, the pinned
# side of `drape` and `curtain`, so the curtain's sphere is in view) and to its side.
VIEW = (0.9, 0.75, -1.2)
LIGHT = (0.2, 1.0, -0.6)  # toward the light: above, from the camera's side
FOV_Y = 35.0  # degrees
SAMPLES = 4  # multisampling (anti-aliased edges), where the driver has it
# Colliders are drawn this much smaller than they are, so that the cloth lying on one (whose
# flat triangles cut slightly into it) is not hidden by it.
COLLIDER_SHRINK = 0.985
FLOOR_DROP = 0.003  # m, the floor patch is drawn this far below its plane, for the same reason

OUTPUT_KINDS = "a .png (the last frame), a .gif (every frame) or a folder/ (one PNG per frame)"


@dataclass(frozen=True)
class Camera:
    eye: np.ndarray
    view_projection: np.ndarray  # 4x4, row-major (p_clip = view_projection @ p)
    size: tuple[int, int]  # (width, height) in pixels

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (column, row from the top) of world points (k, 3)."""
        p = np.hstack([points, np.ones((len(points), 1))]) @ self.view_projection.T
        ndc = p[:, :2] / p[:, 3:4]
        w, h = self.size
        return np.stack([(ndc[:, 0] + 1) / 2 * w, (1 - ndc[:, 1]) / 2 * h], axis=1)


def frame_scene(scene: Scene, size: tuple[int, int], duration: float = 0.0) -> Camera:
    """A fixed camera above and in front of the scene, as close as keeps its bounds (over
    `duration` seconds of motion) in view."""
    lo, hi = scene_bounds(scene, duration)
    centre = (lo + hi) / 2
    back = np.array(VIEW) / np.linalg.norm(VIEW)  # from the centre toward the eye
    right = np.cross((0.0, 1.0, 0.0), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    tan_v = math.tan(math.radians(FOV_Y) / 2)
    tan_h = tan_v * size[0] / size[1]
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    rel = corners - centre
    x, y, z = rel @ right, rel @ up, rel @ back
    distance = 1.06 * float(np.max(z + np.maximum(np.abs(x) / tan_h, np.abs(y) / tan_v)))
    eye = centre + back * distance
    radius = float(np.linalg.norm(hi - lo))
    near, far = max(1e-3, distance - 2 * radius), distance + 6 * radius
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, back
    view[:3, 3] = -view[:3, :3] @ eye
    projection = np.zeros((4, 4))
    projection[0, 0], projection[1, 1] = 1 / tan_h, 1 / tan_v
    projection[2, 2], projection[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    projection[3, 2] = -1
    return Camera(eye, projection @ view, size)


# --- drawing -----------------------------------------------------------------------------


def _matrix(m: np.ndarray) -> bytes:
    """A matrix as a GL uniform: float32, column-major."""
    return np.ascontiguousarray(m.T, dtype=np.float32).tobytes()


@dataclass
class _Shape:
    vao: object
    model: np.ndarray  # vertices to the world, as the scene file places the body
    colour: tuple[float, float, float]
    tiles: bool = False
    body: object = None  # a collider that moves: drawn at its pose for the frame's time

    def model_at(self, t: float) -> np.ndarray:
        if self.body is None or self.body.motion is None:
            return self.model
        return motion_matrix(self.body, t) @ self.model


class Renderer:
    """Draws frames of one scene into an offscreen framebuffer of `device`'s context."""

    def __init__(self, device: gl_context.GLDevice, scene: Scene, size: tuple[int, int], duration: float = 0.0):
        self.gl, self.scene, self.size, self.n = device, scene, size, scene.grid
        self.camera = frame_scene(scene, size, duration)
        self.time = 0.0  # s: the moving colliders are drawn at their pose for this time
        self._vaos: dict = {}  # cloth vertex arrays by the objects they draw from
        self._owned: list = []  # every GL object made here, released by close()
        with device:
            ctx = device.ctx
            samples = min(SAMPLES, ctx.max_samples)
            self.fbo = self._own(
                ctx.framebuffer(
                    [self._own(ctx.renderbuffer(size, 4, samples=samples))],
                    self._own(ctx.depth_renderbuffer(size, samples=samples)),
                )
            )
            self.resolved = self._own(ctx.framebuffer([self._own(ctx.renderbuffer(size, 4))]))
            self.indices = self._own(ctx.buffer(cloth_indices(self.n).tobytes()))
            self.collider_program = self._program("render_collider", {})
            self.shapes = self._collider_shapes()
            self.uploaded = None  # (positions, normals) buffers for backends without GL state

    def _own(self, obj):
        self._owned.append(obj)
        return obj

    def _program(self, name: str, defines: dict):
        version = self.gl.version_code
        vertex = gl_context.shader_source(f"{name}.vert", version, defines)
        fragment = gl_context.shader_source(f"{name}.frag", version, defines)

        def build():
            return self.gl.ctx.program(vertex_shader=vertex, fragment_shader=fragment)

        return self.gl.program(("render", vertex, fragment), build)

    def _collider_shapes(self) -> list[_Shape]:
        ctx, shapes = self.gl.ctx, []

        def vao(vertices, indices):
            return self._own(
                ctx.vertex_array(
                    self.collider_program,
                    [(self._own(ctx.buffer(vertices.tobytes())), "3f 3f", "position", "normal")],
                    index_buffer=self._own(ctx.buffer(indices.tobytes())),
                    index_element_size=4,
                )
            )

        if self.scene.spheres:
            mesh = vao(*sphere_mesh())
            for s in self.scene.spheres:
                model = np.diag([s.radius * COLLIDER_SHRINK] * 3 + [1.0])
                model[:3, 3] = s.center
                shapes.append(_Shape(mesh, model, COLLIDER_COLOUR, body=s))
        if self.scene.cylinders:
            mesh = vao(*cylinder_mesh())
            for c in self.scene.cylinders:
                u = np.array(c.axis)
                e1, e2 = perpendicular(u)
                r, trim = c.radius * COLLIDER_SHRINK, c.radius * (1 - COLLIDER_SHRINK)
                model = np.eye(4)
                model[:3, 0], model[:3, 1], model[:3, 2] = e1 * r, e2 * r, u * (c.length - 2 * trim)
                model[:3, 3] = np.array(c.start) + u * trim
                shapes.append(_Shape(mesh, model, COLLIDER_COLOUR, body=c))
        if self.scene.boxes:
            mesh = vao(*cube_mesh())
            for b in self.scene.boxes:  # the cube scaled to its half extents, then placed
                model = placement_matrix(b) @ np.diag([*(h * COLLIDER_SHRINK for h in b.half_extents), 1.0])
                shapes.append(_Shape(mesh, model, COLLIDER_COLOUR, body=b))
        if self.scene.planes:
            lo, hi = scene_bounds(self.scene)
            half = 4.0 * float(np.max(hi - lo))
            square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
            for p in self.scene.planes:
                nrm = np.array(p.unit_normal)
                e1, e2 = perpendicular(nrm)
                centre = (lo + hi) / 2
                centre = centre - nrm * (np.dot(centre - p.point, nrm) + FLOOR_DROP)  # onto the plane
                corners = centre + half * (square[:, :1] * e1 + square[:, 1:] * e2)
                vertices = np.hstack([corners, np.tile(nrm, (4, 1))]).astype(np.float32)
                square_vao = vao(vertices, np.array([0, 1, 2, 0, 2, 3], np.uint32))
                shapes.append(_Shape(square_vao, np.eye(4), FLOOR_COLOUR, tiles=True, body=p))
        for m in self.scene.meshes:  # its triangles in the body frame, placed by its pose
            shapes.append(
                _Shape(
                    vao(*triangle_mesh(m.geometry.corners, COLLIDER_SHRINK)),
                    placement_matrix(m),
                    COLLIDER_COLOUR,
                    body=m,
                )
            )
        return shapes

    # --- the cloth's sources ---

    def draw_backend(self, backend) -> np.ndarray:
        """A frame of `backend`'s current state: from its device state where it has one."""
        drawable = getattr(backend, "drawable_state", None)
        if drawable is not None:
            return self.draw_state(drawable())
        _, prev = backend.read()
        normals = backend.read_normals()
        if normals is None:
            normals = grid_normals(prev, self.n, np.float32)
        return self.draw_arrays(prev, normals)

    def draw_state(self, state: gl_context.DrawableState) -> np.ndarray:
        """A frame drawn from a GL backend's textures or buffers: no readback of the state."""
        if state.device is not self.gl:
            raise ClothbenchError("the backend's GL context is not the renderer's")
        import moderngl

        with self.gl:
            textures = isinstance(state.positions, moderngl.Texture)
            key = (state.positions.glo, state.normals.glo)
            if key not in self._vaos:
                if textures:  # the vertex shader fetches texel (col, row) by gl_VertexID
                    program = self._program("render_cloth", {"STATE_TEXTURES": ""})
                    content = []
                else:  # storage buffers as vertex buffers: vec4 per particle
                    program = self._program("render_cloth", {})
                    content = [(state.positions, "4f", "position"), (state.normals, "4f", "normal")]
                self._vaos[key] = self._own(
                    self.gl.ctx.vertex_array(program, content, index_buffer=self.indices, index_element_size=4)
                )
            if textures:
                state.positions.use(location=0)
                state.normals.use(location=1)
                self._vaos[key].program["positions"].value = 0
                self._vaos[key].program["normals"].value = 1
            return self._draw(self._vaos[key])

    def draw_arrays(self, positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """A frame of (n*n, 3 or 4) positions and normals from the host, uploaded."""
        with self.gl:
            ctx = self.gl.ctx
            if self.uploaded is None:
                size = self.n * self.n * 16
                self.uploaded = tuple(self._own(ctx.buffer(reserve=size, dynamic=True)) for _ in range(2))
            for buf, values in zip(self.uploaded, (positions, normals)):
                vec4 = np.zeros((self.n * self.n, 4), dtype=np.float32)
                vec4[:, :3] = values[:, :3]
                buf.write(vec4.tobytes())
            state = gl_context.DrawableState(self.gl, *self.uploaded)
        return self.draw_state(state)

    wireframe = False  # draw the cloth's triangles as lines (the viewer's W key)

    def _render(self, cloth_vao) -> None:
        """Draw the colliders and the cloth into the multisampled framebuffer."""
        ctx, cam = self.gl.ctx, self.camera
        light = np.array(LIGHT) / np.linalg.norm(LIGHT)
        self.fbo.use()
        self.fbo.clear(*BACKGROUND, 1.0, depth=1.0)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        for program in (self.collider_program, cloth_vao.program):
            program["view_projection"].write(_matrix(cam.view_projection))
            program["eye"].value = tuple(cam.eye)
            program["light"].value = tuple(light)
        cp = self.collider_program
        for shape in self.shapes:
            model = shape.model_at(self.time)
            cp["model"].write(_matrix(model))
            cp["normal_matrix"].write(_matrix(np.linalg.inv(model[:3, :3]).T))
            cp["base"].value = shape.colour
            cp["tiles"].value = shape.tiles
            shape.vao.render()
        program = cloth_vao.program
        program["n"].value = self.n
        program["checks"].value = float(CHECKS)
        program["colour_a"].value, program["colour_b"].value = CLOTH_COLOURS
        ctx.wireframe = self.wireframe
        try:
            cloth_vao.render()
        finally:
            ctx.wireframe = False

    def _draw(self, cloth_vao) -> np.ndarray:
        self._render(cloth_vao)
        ctx = self.gl.ctx
        ctx.copy_framebuffer(self.resolved, self.fbo)  # resolve the multisampling
        w, h = self.size
        data = self.resolved.read(components=3, alignment=1)
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)[::-1].copy()  # GL's row 0 is the bottom

    def close(self) -> None:
        with self.gl:  # the context is shared: release only what this renderer made
            for obj in reversed(self._owned):
                obj.release()
        self._owned, self._vaos = [], {}


# --- the command ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RenderSettings:
    frames: int = 60
    every: int = 50  # steps between frames
    size: tuple[int, int] = (640, 480)
    fps: float = 25.0  # GIF playback


@dataclass
class RenderReport:
    files: list[Path]
    frames: int
    steps: int
    simulate_s: float = 0.0
    draw_s: float = 0.0
    write_s: float = 0.0
    merged: int = 0  # GIF frames identical to the one before, merged by Pillow into it
    notes: list[str] = field(default_factory=list)


def output_kind(out: str) -> str:
    """'png', 'gif' or 'folder' for an --out value; ClothbenchError for anything else."""
    suffix = Path(out).suffix.lower()
    if out.endswith(("/", "\\")) or Path(out).is_dir() or not suffix:
        return "folder"
    if suffix in (".png", ".gif"):
        return suffix[1:]
    raise ClothbenchError(f"--out must be {OUTPUT_KINDS}, got {out!r}")


def check_settings(settings: RenderSettings) -> None:
    if settings.frames < 1:
        raise ClothbenchError(f"--frames must be >= 1, got {settings.frames}")
    if settings.every < 1:
        raise ClothbenchError(f"--every (steps between frames) must be >= 1, got {settings.every}")
    w, h = settings.size
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ClothbenchError(f"--size must be between 16x16 and 8192x8192, got {w}x{h}")
    if not settings.fps > 0:
        raise ClothbenchError(f"--fps must be > 0, got {settings.fps}")


def render(
    scene: Scene,
    solver: Solver,
    backend_name: str,
    options: BackendOptions,
    settings: RenderSettings,
    out: str,
    on_frame=None,
) -> RenderReport:
    """Simulate `settings.frames` x `settings.every` steps of `scene` stepped by `solver` on
    `backend_name`, drawing a frame after every `every` steps, into `out` (see OUTPUT_KINDS)."""
    kind = output_kind(out)
    check_settings(settings)
    path = Path(out)
    _writable(path if kind == "folder" else path.parent)  # fail before simulating, not after
    takes = capabilities(backend_name, solver.name)
    # normals from the step where the backend computes them (else draw_backend's grid_normals);
    # options.gl is the renderer's context, passed on to the backend where it takes one
    backend_options = replace(options, normals=takes.normals, gl=options.gl if takes.gl else "egl")
    report = RenderReport([], settings.frames, settings.frames * settings.every)
    images = []
    with create_backend(backend_name, scene, solver, backend_options) as backend:
        device = backend.gl if hasattr(backend, "drawable_state") else gl_context.get_device(options.gl)
        renderer = Renderer(device, scene, settings.size, settings.frames * settings.every * solver.dt)
        try:
            backend.upload(*backend.initial_state())
            for frame in range(1, settings.frames + 1):
                t0 = time.perf_counter()
                backend.advance(settings.every)
                backend.synchronize()
                t1 = time.perf_counter()
                report.simulate_s += t1 - t0
                if kind != "png" or frame == settings.frames:  # a PNG is the last frame only
                    # the drawn state is the one the last step read, x((steps - 1) dt): the colliders then
                    renderer.time = (frame * settings.every - 1) * solver.dt
                    images.append(renderer.draw_backend(backend))
                    t2 = time.perf_counter()
                    report.draw_s += t2 - t1
                    if kind == "folder":  # written as they come: an interrupted render keeps them
                        report.files.append(_save_png(images.pop(), path / f"frame_{frame:04d}.png"))
                        report.write_s += time.perf_counter() - t2
                if on_frame is not None:
                    on_frame(frame)
        finally:
            renderer.close()
    _write_images(report, kind, images, path, settings.fps)
    if report.merged:
        report.notes.append(
            f"{report.merged} frames were identical to the one before and were merged into it "
            "(their time added): the GIF plays the same, with fewer frames"
        )
    return report


def render_exported(exported, size: tuple[int, int], out: str, frame: int | None, fps: float, gl: str = "egl"):
    """Draw the frames of a USD `run --export` wrote (reports/export.py's Exported) into `out`:
    a .png is one frame (`frame`, default the last), a .gif or a folder every frame (a folder's
    files named by frame index, as the export's are). Each frame is drawn from the file's points
    and normals, its colliders where they were at the frame's time."""
    kind = output_kind(out)
    path = Path(out)
    _writable(path if kind == "folder" else path.parent)
    chosen = [exported.check_frame(frame if frame is not None else exported.frames - 1)] if kind == "png" else None
    frames = chosen or list(range(exported.frames))
    report = RenderReport([], len(frames), exported.step(frames[-1]))
    duration = exported.time(exported.frames - 1)
    renderer = Renderer(gl_context.get_device(gl), exported.scene, size, duration)
    images = []
    try:
        for f in frames:
            t0 = time.perf_counter()
            renderer.time = exported.time(f)  # the state after step s is x(s dt), its colliders then
            image = renderer.draw_arrays(exported.points[f], exported.normals[f])
            t1 = time.perf_counter()
            report.draw_s += t1 - t0
            if kind == "folder":
                report.files.append(_save_png(image, path / f"frame_{f:04d}.png"))
                report.write_s += time.perf_counter() - t1
            else:
                images.append(image)
    finally:
        renderer.close()
    _write_images(report, kind, images, path, fps)
    return report


def _write_images(report: RenderReport, kind: str, images: list, path: Path, fps: float) -> None:
    """The frames kept for a PNG (the last) or a GIF (every one) written to `path`, into
    `report` with the time it took; a folder's frames were written as they came."""
    t0 = time.perf_counter()
    if kind == "png":
        report.files.append(_save_png(images[-1], path))
    elif kind == "gif":
        report.merged = _written(path, lambda: write_gif(images, path, fps))
        report.files.append(path)
    report.write_s += time.perf_counter() - t0


def _writable(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ClothbenchError(f"cannot write into {folder}: {e.strerror or e}") from None


def _written(path: Path, write):
    """write(), with an OSError as a one-line ClothbenchError naming `path`."""
    try:
        return write()
    except OSError as e:
        raise ClothbenchError(f"cannot write {path}: {e.strerror or e}") from None


def _save_png(image: np.ndarray, path: Path) -> Path:
    from PIL import Image

    _written(path, lambda: Image.fromarray(image).save(path))
    return path


def write_gif(images: list[np.ndarray], out: Path, fps: float) -> int:
    """An animated GIF, looping, every frame on one palette (no colour flicker from frame
    to frame). Returns how many frames Pillow merged into the one before (identical)."""
    from PIL import Image

    # the palette of a few frames side by side: the colours of the whole animation
    sample = [images[i] for i in sorted({0, len(images) // 3, 2 * len(images) // 3, len(images) - 1})]
    palette = Image.fromarray(np.concatenate(sample, axis=1)).quantize(255, method=Image.Quantize.MEDIANCUT)
    dither = Image.Dither.FLOYDSTEINBERG
    frames = [Image.fromarray(im).quantize(palette=palette, dither=dither) for im in images]
    frames[0].save(out, save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0, optimize=False)
    with Image.open(out) as written:
        return len(images) - written.n_frames
