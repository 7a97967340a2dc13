"""The cloth out to the tools users already have (docs/export.md): `clothbench run --export`
writes a USD stage (a time-sampled mesh with normals, each collider its own prim) or a folder
of OBJ or PLY frames, and an exported USD is read back for `render --from` and `view --from`.

A frame is the state `run --save` writes, `pos` after that many steps (x(step dt)), with
the normals of docs/normals.md computed from those very positions (harness/normals.py, as the
renderer computes them for a readback): a backend's own normals belong to `prev`, one step
behind (docs/normals.md, "Which positions"), so they would not be the exported points'.
Colliders are placed at their pose for the frame's time, step dt (docs/semantics.md, "Moving
colliders": a step's collisions use the pose at its end).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.harness.normals import grid_normals
from clothbench.reports.meshes import cloth_indices, perpendicular
from clothbench.reports.render_bounds import scene_bounds
from clothbench.model.scene import Scene, body_pose, load_setup
from clothbench.model.solver import Solver

USD_SUFFIXES = (".usd", ".usda", ".usdc")  # .usd is the binary crate format unless named .usda
FRAME_FORMATS = ("obj", "ply")
# OBJ is text: 10 decimal places reproduce every float32 coordinate of magnitude >= 2^-10 m
# exactly (its half-spacing, 2^-34, is above the 5e-11 rounding) and any other within 5e-11 m.
# PLY is binary and holds the float32 values exactly.
OBJ_DIGITS = 10
OBJ_TOLERANCE = 0.5 * 10.0**-OBJ_DIGITS  # m
# The floor patch a plane is drawn as: this many times the scene's box on a side, about its centre.
PLANE_PATCH = 4.0
WRITTEN_KINDS = {"sphere", "cylinder", "box", "plane"}  # the analytic collider kinds _colliders writes (and meshes)
METADATA_KEY = "clothbench"  # the stage's customLayerData entry naming the run (read back by read_usd)
INSTALL = "pip install usd-core (or clothbench's extra: pip install 'clothbench[export]')"


@dataclass(frozen=True)
class ExportTarget:
    path: Path
    kind: str  # "usd", or one of FRAME_FORMATS for a folder of frames


def export_target(out: str | None, every: int | None, frame_format: str | None) -> ExportTarget | None:
    """--export's target, or one line saying why not, before any work: the suffix, the folder
    it goes into, and the options that only apply to an export."""
    from clothbench.harness.preflight import check_writable

    if out is None:
        for option, value in (("--export-every", every), ("--export-format", frame_format)):
            if value is not None:
                raise ClothbenchError(f"{option} applies to --export only: add --export FILE.usd or --export FOLDER/")
        return None
    if every is not None and every < 1:
        raise ClothbenchError(f"--export-every must be >= 1 (steps between exported frames), got {every}")
    path = Path(out)
    folder = out.endswith(("/", os.sep)) or path.is_dir()
    suffix = path.suffix.lower()
    if folder and suffix in USD_SUFFIXES:
        raise ClothbenchError(
            f"--export {out!r} is a folder with a {suffix} suffix: name a file (anim.usd) or a folder (frames/)"
        )
    if folder or not suffix:
        kind = frame_format or FRAME_FORMATS[0]
        # a longer earlier export's last frames would stay beside this one's and read as its own
        old = sorted(p.name for f in FRAME_FORMATS for p in path.glob(f"frame_*.{f}")) if path.is_dir() else []
        if old:
            raise ClothbenchError(
                f"--export {out!r} already holds {len(old)} frame file{'s' * (len(old) != 1)} ({old[0]} ...) "
                "from an earlier export: remove them or name another folder"
            )
        check_writable(path / f"frame_0000.{kind}", "--export", new_folder=True)
        return ExportTarget(path, kind)
    if suffix not in USD_SUFFIXES:
        raise ClothbenchError(
            f"--export takes a {', '.join(USD_SUFFIXES)} file or a folder/ (OBJ or PLY frames), got {out!r}"
        )
    if frame_format is not None:
        raise ClothbenchError(f"--export-format chooses the files of a folder of frames, and {out!r} is a USD file")
    usd()  # installed, or said now rather than after the run
    return ExportTarget(check_writable(path, "--export"), "usd")


def usd():
    """OpenUSD's Python package (usd-core) with the modules used here, or one line naming it."""
    try:
        import pxr.Gf
        import pxr.Usd
        import pxr.UsdGeom
        import pxr.Vt
    except ModuleNotFoundError:
        raise ClothbenchError(f"a USD export needs OpenUSD's Python library (pxr): {INSTALL}") from None
    return pxr


# --- writing --------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunInfo:
    """What the file says it came from: enough to load its scene again and name its run."""

    scene: str  # the --scene given: a built-in name, or a scene file's absolute path
    grid: int
    dt: float
    solver: str  # Solver.spec
    every: int  # steps between frames
    steps: int  # steps of the run
    backend: str
    mode: str


def scene_spec(name_or_path: str) -> str:
    """--scene as the file records it: a scene file by its absolute path, so that a file read
    back from another folder still finds it."""
    path = Path(name_or_path)
    return str(path.resolve()) if name_or_path.endswith(".toml") or path.exists() else name_or_path


def frame_steps(steps: int, every: int) -> list[int]:
    """The steps a frame is written after: 0 (the start), every K steps, and the last step."""
    return sorted({*range(0, steps, every), steps})


class UsdWriter:
    """One stage: /World/Cloth (a Mesh, points, normals and extent per frame), and each
    collider under /World/Colliders, a moving one's transform per frame. One time code is one
    exported frame (`step / every`), so timeCodesPerSecond is 1 / (every dt): usdview plays it
    in real time and Blender imports one of its frames per exported frame."""

    def __init__(self, path: Path, scene: Scene, info: RunInfo):
        pxr = usd()
        Usd, UsdGeom, Vt = pxr.Usd, pxr.UsdGeom, pxr.Vt
        self.path, self.scene, self.info = path, scene, info
        self.stage = Usd.Stage.CreateInMemory()
        stage = self.stage
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        rate = 1.0 / (info.every * info.dt)
        stage.SetTimeCodesPerSecond(rate)
        stage.SetFramesPerSecond(rate)
        stage.SetStartTimeCode(0.0)
        stage.SetEndTimeCode(info.steps / info.every)
        stage.GetRootLayer().customLayerData = {METADATA_KEY: {k: v for k, v in vars(info).items()}}
        world = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(world.GetPrim())
        n = scene.grid
        self.cloth = UsdGeom.Mesh.Define(stage, "/World/Cloth")
        triangles = cloth_indices(n)
        self.cloth.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(triangles), 3, np.int32)))
        self.cloth.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(triangles.reshape(-1).astype(np.int32)))
        # cloth_indices winds each triangle counter-clockwise seen from the normals' side
        self.cloth.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        self.cloth.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # the triangles as they are, not a limit surface
        self.cloth.CreateDoubleSidedAttr(True)
        self.cloth.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        self._points = self.cloth.CreatePointsAttr()
        self._normals = self.cloth.CreateNormalsAttr()
        self._extent = self.cloth.CreateExtentAttr()
        self._moving = [(xf, body, local) for xf, body, local in self._colliders() if body.motion is not None]
        unwritten = sorted({c.kind for c in scene.colliders} - WRITTEN_KINDS)
        # a kind the scene model gained after this writer (said, not dropped in silence)
        self.notes = [f"{kind} colliders are not in the USD (no writer for them yet)" for kind in unwritten]

    def frame(self, step: int, pos: np.ndarray) -> None:
        pxr = usd()
        Usd, Vt = pxr.Usd, pxr.Vt
        code = Usd.TimeCode(step / self.info.every)
        points = np.ascontiguousarray(pos[:, :3], dtype=np.float32)
        normals = grid_normals(points, self.scene.grid, np.float32)
        self._points.Set(Vt.Vec3fArray.FromNumpy(points), code)
        self._normals.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals)), code)
        self._extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([points.min(axis=0), points.max(axis=0)])), code)
        for op, body, local in self._moving:
            op.Set(_usd_matrix(_pose(body, step * self.info.dt) @ local), code)

    def close(self) -> Path:
        """Written next to the target and moved onto it: an interrupted run leaves the old file
        or the new one, never half (the partial name keeps the suffix USD picks its format by)."""
        partial = self.path.with_name(f".{self.path.stem}.partial{self.path.suffix}")
        if not self.stage.GetRootLayer().Export(str(partial)):
            raise ClothbenchError(f"cannot write {self.path}: OpenUSD could not export the stage")
        partial.replace(self.path)
        return self.path

    def _colliders(self):
        """Each collider a prim under /World/Colliders with one transform op (the body's pose
        times the shape's own placement in the body frame): (op, body, local matrix)."""
        pxr = usd()
        Gf, UsdGeom = pxr.Gf, pxr.UsdGeom
        scene, stage, made = self.scene, self.stage, []
        UsdGeom.Scope.Define(stage, "/World/Colliders")

        def place(prim, body, local):
            op = prim.AddTransformOp()
            op.Set(_usd_matrix(_pose(body, 0.0) @ local))  # the default: where a static one always is
            made.append((op, body, local))

        for i, s in enumerate(scene.spheres):
            sphere = UsdGeom.Sphere.Define(stage, f"/World/Colliders/sphere_{i}")
            sphere.CreateRadiusAttr(s.radius)
            sphere.CreateExtentAttr([Gf.Vec3f(-s.radius), Gf.Vec3f(s.radius)])
            place(sphere, s, np.eye(4))
        for i, c in enumerate(scene.cylinders):  # USD's is centred on its Z axis; the body frame starts at `start`
            cylinder = UsdGeom.Cylinder.Define(stage, f"/World/Colliders/cylinder_{i}")
            cylinder.CreateAxisAttr(UsdGeom.Tokens.z)
            cylinder.CreateRadiusAttr(c.radius)
            cylinder.CreateHeightAttr(c.length)
            half = c.length / 2
            cylinder.CreateExtentAttr([Gf.Vec3f(-c.radius, -c.radius, -half), Gf.Vec3f(c.radius, c.radius, half)])
            u = np.array(c.axis)
            local = np.eye(4)
            local[:3, 0], local[:3, 1] = perpendicular(u)
            local[:3, 2], local[:3, 3] = u, u * half
            place(cylinder, c, local)
        for i, b in enumerate(scene.boxes):  # USD's cube has edges of 2: scaled to the half extents in the body frame
            box = UsdGeom.Cube.Define(stage, f"/World/Colliders/box_{i}")
            box.CreateSizeAttr(2.0)
            box.CreateExtentAttr([Gf.Vec3f(-1.0), Gf.Vec3f(1.0)])
            place(box, b, np.diag([*b.half_extents, 1.0]))
        lo, hi = scene_bounds(scene)
        half_patch = PLANE_PATCH * float(np.max(hi - lo)) / 2
        for i, p in enumerate(scene.planes):  # a square patch of the half-space's surface, centred below the scene
            e1, e2 = perpendicular(np.array(p.unit_normal))
            centre = (lo + hi) / 2 - np.array(p.point)
            centre -= np.dot(centre, p.unit_normal) * np.array(p.unit_normal)  # onto the plane, in the body frame
            square = [centre + half_patch * (a * e1 + b * e2) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            plane = self._mesh(f"/World/Colliders/plane_{i}", np.array(square), np.array([[0, 1, 2, 3]]))
            place(plane, p, np.eye(4))
        for i, m in enumerate(scene.meshes):  # its triangles in the body frame, placed by its pose
            corners = m.geometry.corners.reshape(-1, 3)
            mesh = self._mesh(f"/World/Colliders/mesh_{i}", corners, np.arange(len(corners)).reshape(-1, 3))
            place(mesh, m, np.eye(4))
        return made

    def _mesh(self, where: str, points: np.ndarray, faces: np.ndarray):
        pxr = usd()
        UsdGeom, Vt = pxr.UsdGeom, pxr.Vt
        mesh = UsdGeom.Mesh.Define(self.stage, where)
        points = np.ascontiguousarray(points, dtype=np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), faces.shape[1], np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDoubleSidedAttr(True)
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([points.min(axis=0), points.max(axis=0)])))
        return mesh


def _pose(body, t: float) -> np.ndarray:
    """The body-to-world 4x4 of a collider at time t (colliders/motion.py), float64."""
    rotation, translation = body_pose(body, t)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


def _usd_matrix(m: np.ndarray):
    """A column-vector 4x4 as USD's Gf.Matrix4d, which multiplies row vectors: its transpose."""
    Gf = usd().Gf
    return Gf.Matrix4d(*m.T.reshape(-1).tolist())


class FramesWriter:
    """A folder of frame_0000.obj (or .ply), ... : the cloth alone, one file per frame as it
    comes (an interrupted run keeps those written), through trimesh."""

    def __init__(self, folder: Path, scene: Scene, info: RunInfo, kind: str):
        self.folder, self.scene, self.info, self.kind = folder, scene, info, kind
        self.faces = cloth_indices(scene.grid)
        self.files: list[Path] = []
        self.notes: list[str] = []
        try:
            folder.mkdir(exist_ok=True)
        except OSError as e:
            raise ClothbenchError(f"cannot write --export {folder}: {e.strerror or e}") from None

    def frame(self, step: int, pos: np.ndarray) -> None:
        import trimesh
        from trimesh.exchange.obj import export_obj
        from trimesh.exchange.ply import export_ply

        points = np.ascontiguousarray(pos[:, :3], dtype=np.float32)
        normals = grid_normals(points, self.scene.grid, np.float32)
        mesh = trimesh.Trimesh(points.astype(np.float64), self.faces, vertex_normals=normals, process=False)
        if self.kind == "obj":
            data = export_obj(mesh, include_normals=True, digits=OBJ_DIGITS).encode()
        else:
            data = export_ply(mesh, encoding="binary", vertex_normal=True)
        path = self.folder / f"frame_{len(self.files):04d}.{self.kind}"
        try:
            path.write_bytes(data)
        except OSError as e:
            raise ClothbenchError(f"cannot write {path}: {e.strerror or e}") from None
        self.files.append(path)

    def close(self) -> Path:
        return self.folder


def open_writer(target: ExportTarget, scene: Scene, info: RunInfo):
    if target.kind == "usd":
        return UsdWriter(target.path, scene, info)
    return FramesWriter(target.path, scene, info, target.kind)


def export_replay(backend, steps: int, writer) -> tuple[int, np.ndarray]:
    """Step `backend` again from its start, untimed, reading it back after each frame's steps
    (frame_steps) and writing the frame: (frames written, the last state). Stops early at a
    state that is no longer finite (a blown-up run keeps the frames before it)."""
    pos, prev = backend.initial_state()
    backend.upload(pos, prev)
    done, frames = 0, 0
    for step in frame_steps(steps, writer.info.every):
        if step > done:
            backend.advance(step - done)
            backend.synchronize()
            pos, _ = backend.read()
            done = step
        if not np.isfinite(pos[:, :3]).all():
            break
        writer.frame(step, pos)
        frames += 1
    return frames, pos


# --- reading back ---------------------------------------------------------------------------


@dataclass
class Exported:
    """An exported USD read back: the scene it was run on, and its frames' cloth."""

    path: Path
    info: RunInfo
    scene: Scene
    solver: Solver
    codes: list[float]  # the cloth's time codes, one a frame
    points: list[np.ndarray]  # (n*n, 3) float32 each
    normals: list[np.ndarray]

    @property
    def frames(self) -> int:
        return len(self.codes)

    def step(self, frame: int) -> int:
        return round(self.codes[frame] * self.info.every)

    def time(self, frame: int) -> float:
        """Seconds simulated at `frame`: where its colliders are."""
        return self.step(frame) * self.info.dt

    def check_frame(self, frame: int) -> int:
        if not 0 <= frame < self.frames:
            raise ClothbenchError(f"--frame {frame}: {self.path} has frames 0 to {self.frames - 1}")
        return frame


def read_usd(path: str | Path) -> Exported:
    """An exported USD's run and every frame of its cloth, or one line saying why not."""
    pxr = usd()
    Usd, UsdGeom = pxr.Usd, pxr.UsdGeom
    path = Path(path)
    if not path.is_file():
        raise ClothbenchError(f"--from {path}: no such file")
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception:  # pxr's Tf.ErrorException, whose text is a C++ source location
        raise ClothbenchError(f"--from {path}: OpenUSD cannot open it (not a USD file, or a damaged one)") from None
    meta = stage.GetRootLayer().customLayerData.get(METADATA_KEY)
    cloth = UsdGeom.Mesh.Get(stage, "/World/Cloth")
    if not meta or not cloth:
        raise ClothbenchError(f"--from {path}: not a file `clothbench run --export` wrote (no {METADATA_KEY} run)")
    info = RunInfo(**{k: meta[k] for k in RunInfo.__dataclass_fields__})
    try:
        setup = load_setup(info.scene).replace(grid=info.grid, dt=info.dt)
    except ClothbenchError as e:
        raise ClothbenchError(f"--from {path}: its scene {info.scene!r} cannot be loaded now: {e}") from None
    codes = list(cloth.GetPointsAttr().GetTimeSamples())
    points = [np.array(cloth.GetPointsAttr().Get(c), dtype=np.float32) for c in codes]
    normals = [np.array(cloth.GetNormalsAttr().Get(c), dtype=np.float32) for c in codes]
    if not codes or any(p.shape != (info.grid**2, 3) for p in points):
        raise ClothbenchError(f"--from {path}: its cloth is not {info.grid}x{info.grid} points at every frame")
    solver = setup.solver_for(info.solver) if info.solver != setup.solver.spec else setup.solver
    return Exported(path, info, setup.scene, solver, codes, points, normals)


def usd_file(text: str) -> str:
    """--from's argument: a USD file by its suffix, or one line."""
    if Path(text).suffix.lower() not in USD_SUFFIXES:
        raise ClothbenchError(f"--from takes a USD file `run --export` wrote ({', '.join(USD_SUFFIXES)}), got {text!r}")
    return text


__all__ = [
    "ExportTarget",
    "RunInfo",
    "UsdWriter",
    "FramesWriter",
    "Exported",
    "export_target",
    "open_writer",
    "export_replay",
    "frame_steps",
    "read_usd",
    "scene_spec",
    "usd_file",
    "OBJ_TOLERANCE",
]
