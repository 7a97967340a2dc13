"""Speed against error taken to its end: of the configurations an accuracy run measured, the
cheapest whose error stays under a bound, the runners-up, and what would have to give when
none does.

A configuration is one accuracy row: a backend in one mode (its BackendOptions), a solver
(Verlet, or PBD with its method, iterations and substeps) and a dt, stepped to the run's
simulated time T. Its cost is the row's measured ms of compute per simulated second; its
error the row's discretisation error (disc_max or disc_rms: against the converged float64
reference of its own model, analysis/convergence.py), which is what the user's cloth is
wrong by at T. A row qualifies for a bound E when its error plus its reference's own
uncertainty is at most E: the true error is then at most E too (triangle inequality; the
uncertainty is a max norm, so it bounds the RMS part as well).

Only configurations that can run here are advised: the row's backend is usable and today's
plan of variants (harness/plan.py) still has its mode. A row whose label has since been
renamed (an older CSV's 'wg=64' is today's 'ls=auto') is matched by what its mode says:
precision, strict or fast, transfer, generic.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

from clothbench.analysis.convergence import AccuracyRow
from clothbench.backends import BACKENDS, BackendOptions, availability
from clothbench.environment import cpu_model
from clothbench.errors import ClothbenchError
from clothbench.harness.plan import Variant, plan_variants
from clothbench.model.scene import Setup
from clothbench.model.solver import ITERATIVE, Solver
from clothbench.variant_names import Mode, model_name, option_flags

METRICS = {"max": "disc_max", "rms": "disc_rms"}  # --metric -> the accuracy CSV's column
DEFAULT_METRIC = "max"  # "stays under E": every particle, not the average one
RUNNERS_UP = 4
# the columns advise reads; the others of AccuracyRow may be missing from an older CSV
REQUIRED = (
    "scene",
    "grid",
    "start",
    "damping",
    "time_s",
    "backend",
    "label",
    "mode",
    "device",
    "dt",
    "steps",
    "solver",
    "pbd_method",
    "iterations",
    "substeps",
    "status",
    "ms_per_step",
    "ms_per_sim_s",
    "disc_rms",
    "disc_max",
    "ref_model",
    "ref_converged",
    "ref_uncertainty",
)


@dataclass
class AccuracyRun:
    """An accuracy run's rows and where its costs were measured."""

    rows: list[AccuracyRow]
    source: str  # the CSV's path, or "measured here"
    cpu: str | None = None  # the machine the costs were measured on, where known
    cpu_from: str = ""  # how that is known
    stiffness: float | None = None  # the CSV's stiffness column, where it has one

    @property
    def time_s(self) -> float:
        return self.rows[0].time_s

    @property
    def grid(self) -> int:
        return self.rows[0].grid

    @property
    def scene(self) -> str:
        return self.rows[0].scene


def _parse(value: str, kind: str):
    kind = kind.replace(" ", "")
    if kind == "int":
        return int(value)
    if kind == "float":
        return float(value)
    if kind == "bool":
        if value not in ("True", "False"):
            raise ValueError(f"not True or False: {value!r}")
        return value == "True"
    if kind == "int|None":
        return int(value) if value else None
    return value


def read_accuracy_csv(path: str | Path) -> AccuracyRun:
    """The rows of a `clothbench accuracy` CSV, or one line saying why it is not one."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            columns = reader.fieldnames or []
            records = list(reader)
    except UnicodeDecodeError:
        raise ClothbenchError(f"{path} is not a clothbench accuracy CSV (not UTF-8 text)") from None
    except (OSError, csv.Error) as e:
        raise ClothbenchError(f"cannot read {path}: {getattr(e, 'strerror', None) or e}") from None
    missing = [c for c in REQUIRED if c not in columns]
    if missing:
        raise ClothbenchError(
            f"{path} is not an accuracy CSV of clothbench (no {', '.join(missing[:3])} column"
            f"{'s' if len(missing) > 1 else ''}); advise reads what `clothbench accuracy` writes"
        )
    if not records:
        raise ClothbenchError(f"{path} has no rows")
    kinds = {f.name: f.type for f in dataclasses.fields(AccuracyRow)}
    rows = []
    for n, record in enumerate(records, start=2):  # line 1 is the header
        if record.get("in_fit") == "" and record.get("status") is not None:  # written as measured, not fitted
            raise ClothbenchError(f"{path} is an unfinished accuracy run: finish it with clothbench accuracy --resume")
        try:
            rows.append(AccuracyRow(**{k: _parse(v, kinds[k]) for k, v in record.items() if k in kinds}))
        except (TypeError, ValueError) as e:
            raise ClothbenchError(f"{path}, line {n}: not an accuracy row ({e})") from None
    stiffness = None
    if "stiffness" in columns:
        values = {float(r["stiffness"]) for r in records}
        stiffness = values.pop() if len(values) == 1 else float("nan")
    if "cpu" in columns and (cpus := {r["cpu"] for r in records if r["cpu"]}):
        cpu, cpu_from = " / ".join(sorted(cpus)), "the CSV's cpu column"
    elif cpus := {r.device for r in rows if r.backend == "numpy" and r.device not in ("", "?")}:
        cpu, cpu_from = " / ".join(sorted(cpus)), "the numpy rows' device; the CSV has no cpu column"
    else:
        cpu, cpu_from = None, ""
    return AccuracyRun(rows, str(path), cpu, cpu_from, stiffness)


def measured_here(rows: list[AccuracyRow]) -> AccuracyRun:
    """An AccuracyRun of rows run_accuracy has just measured on this machine."""
    return AccuracyRun(list(rows), "measured here", cpu_model(), "this machine, now")


def solver_of(row: AccuracyRow, setup: Setup) -> Solver:
    """The solver a row was stepped by: the scene file's settings with the row's own."""
    if row.solver == "verlet":
        return setup.solver_for("verlet").replace(dt=row.dt)
    if row.solver == "pbd" and row.pbd_method:
        solver = setup.solver_for(f"pbd-{row.pbd_method}")
        return solver.replace(dt=row.dt, iterations=row.iterations, substeps=row.substeps)
    if row.solver == "vbd":
        return setup.solver_for("vbd").replace(dt=row.dt, iterations=row.iterations, substeps=row.substeps)
    raise ClothbenchError(f"row {row.label!r}: unknown solver {row.solver!r} {row.pbd_method!r}")


def check_matches(run: AccuracyRun, setup: Setup) -> None:
    """Refuse a run of another scene, or of this one with other constants or solver
    settings than the scene file's: its errors and costs would answer another question."""
    src, scene = run.source, setup.scene

    def one(what: str) -> set:
        values = {getattr(r, what) for r in run.rows}
        if len(values) != 1:
            raise ClothbenchError(f"{src} mixes {what} values {sorted(map(str, values))}: not one accuracy run")
        return values

    if one("scene") != {scene.name}:
        raise ClothbenchError(f"{src} is an accuracy run of scene {run.scene!r}, not {scene.name!r}")
    one("time_s"), one("grid")
    if one("start") != {setup.solver.start}:
        raise ClothbenchError(
            f"{src} was run with start {run.rows[0].start!r}; scene {scene.name} starts {setup.solver.start!r}"
        )
    damping = run.rows[0].damping
    if not math.isclose(damping, scene.damping, rel_tol=1e-9, abs_tol=1e-15):
        raise ClothbenchError(f"{src} was run with damping {damping:g}; scene {scene.name} has {scene.damping:g}")
    if run.stiffness is not None and not math.isclose(run.stiffness, scene.stiffness, rel_tol=1e-9):
        raise ClothbenchError(
            f"{src} was run with stiffness {run.stiffness:g}; scene {scene.name} has {scene.stiffness:g}"
        )
    for row in run.rows:
        if row.backend not in BACKENDS:
            raise ClothbenchError(f"{src}: unknown backend {row.backend!r} (known: {', '.join(BACKENDS)})")
        want = model_name(solver_of(row, setup))
        if row.ref_model != want:
            raise ClothbenchError(
                f"{src}: {row.label} was measured as model {row.ref_model!r}; scene {scene.name}'s is {want!r}"
            )


@dataclass(frozen=True)
class Configuration:
    """Everything `clothbench run` needs to step one configuration to T."""

    backend: str
    options: BackendOptions
    solver: Solver
    grid: int
    steps: int
    label: str  # today's variant name (Variant.name)

    def run_args(self, scene_arg: str) -> list[str]:
        """The `clothbench run` command line, as argv."""
        s = self.solver
        args = ["clothbench", "run", "--backend", self.backend, "--scene", scene_arg, "--grid", str(self.grid),
                "--solver", s.name, "--dt", repr(s.dt), "--steps", str(self.steps)]  # fmt: skip
        if s.name == "pbd":
            args += ["--pbd-method", s.method]
        if s.name in ITERATIVE:
            args += ["--iterations", str(s.iterations), "--substeps", str(s.substeps)]
        return args + option_flags(self.options)


@lru_cache(maxsize=None)
def _planned(backend: str, solver: Solver) -> tuple[Variant, ...]:
    return tuple(plan_variants([backend], [solver])[0])


def _agrees(mode: str, v: Variant) -> bool:
    """Whether a mode string from a CSV says what `v`'s options are."""
    said = Mode.parse(mode)
    o, caps = v.options, v.capabilities
    if (said.precision == "f64") != (o.precision == "f64") or said.generic != o.generic:
        return False
    if said.strict is not None and said.strict != o.strict:
        return False
    if caps.transfers:
        named = said.transfer if said.transfer in caps.transfers else caps.transfers[0]
        return (o.transfer or caps.transfers[0]) == named
    return True


def configuration_for(row: AccuracyRow, setup: Setup) -> Configuration | str:
    """The runnable configuration of a row, or why it cannot run here."""
    avail = availability(row.backend)
    if not avail.usable:
        return f"{row.backend} cannot run here: {avail.reason}"
    solver = solver_of(row, setup)
    variants = _planned(row.backend, solver.replace(dt=type(solver).dt))
    same = [v for v in variants if v.name == row.label] or [v for v in variants if _agrees(row.mode, v)]
    if len(same) != 1:
        today = ", ".join(v.name for v in variants) or "none"
        return f"today's {row.backend} variants ({today}) do not include {row.label!r}"
    return Configuration(row.backend, same[0].options, solver, row.grid, row.steps, same[0].name)


@dataclass
class Pick:
    """A measured configuration that can run here, with its error under the chosen metric."""

    row: AccuracyRow
    config: Configuration
    error: float
    uncertainty: float  # of its reference (max norm); inf when unknown and not converged

    @property
    def cost(self) -> float:
        return self.row.ms_per_sim_s

    @property
    def bound(self) -> float:
        """What the error is at most: measured plus the reference's uncertainty."""
        return self.error + self.uncertainty

    @property
    def model(self) -> str:
        return self.row.ref_model

    def as_dict(self, scene_arg: str) -> dict:
        r, s = self.row, self.config.solver
        argv = self.config.run_args(scene_arg)
        return {
            "backend": r.backend,
            "variant": self.config.label,
            "measured_as": r.label,
            "device": r.device,
            "options": {
                k: v for k, v in dataclasses.asdict(self.config.options).items() if v != getattr(BackendOptions(), k)
            },
            "solver": dataclasses.asdict(s) | {"name": s.name},
            "model": r.ref_model,
            "grid": r.grid,
            "dt": r.dt,
            "steps": r.steps,
            "time_s": r.time_s,
            "ms_per_sim_s": r.ms_per_sim_s,
            "ms_per_step": r.ms_per_step,
            "error": self.error,
            "error_bound": self.bound,
            "disc_rms": r.disc_rms,
            "disc_max": r.disc_max,
            "vs_verlet_rms": r.vs_verlet_rms,
            "vs_verlet_max": r.vs_verlet_max,
            "argv": argv[1:],
            "command": " ".join(argv),
        }


@dataclass
class Prediction:
    """A smaller dt than was measured, predicted from a line's fitted order."""

    pick: Pick  # the line's finest measured dt
    dt: float  # T / steps: a whole number of steps
    steps: int
    cost: float  # ms per simulated second, at the measured cost per step

    def as_dict(self, scene_arg: str) -> dict:
        return {
            "from": self.pick.as_dict(scene_arg),
            "order": self.pick.row.order,
            "dt": self.dt,
            "steps": self.steps,
            "ms_per_sim_s": self.cost,
        }


@dataclass
class Group:
    """The cheapest qualifying configuration of one model or backend, else its smallest error."""

    name: str
    cheapest: Pick | None
    closest: Pick


@dataclass
class Advice:
    run: AccuracyRun
    metric: str
    max_error: float
    choice: Pick | None
    runners_up: list[Pick]
    by_model: list[Group]  # every model but the choice's
    by_backend: list[Group]  # every backend but the choice's
    closest: Pick | None  # the smallest error measured
    cheapest: Pick | None  # the cheapest configuration measured, whatever its error
    predictions: list[Prediction]  # when none qualifies: smaller dts, cheapest first
    left_out: list[tuple[str, str]] = field(default_factory=list)  # (label, why)

    def as_dict(self, scene_arg: str) -> dict:
        def pick(p):
            return p.as_dict(scene_arg) if p else None

        def groups(gs):
            return [{"name": g.name, "cheapest": pick(g.cheapest), "closest": pick(g.closest)} for g in gs]

        here = cpu_model()
        return {
            "scene": self.run.scene,
            "grid": self.run.grid,
            "time_s": self.run.time_s,
            "metric": self.metric,
            "column": METRICS[self.metric],
            "max_error": self.max_error,
            "source": self.run.source,
            "measured_on": self.run.cpu,
            "measured_on_from": self.run.cpu_from,
            "this_machine": here,
            "costs_from_this_machine": self.run.cpu == here,
            "choice": pick(self.choice),
            "runners_up": [pick(p) for p in self.runners_up],
            "by_model": groups(self.by_model),
            "by_backend": groups(self.by_backend),
            "closest": pick(self.closest),
            "cheapest": pick(self.cheapest),
            "predictions": [p.as_dict(scene_arg) for p in self.predictions],
            "left_out": [{"label": label, "why": why} for label, why in self.left_out],
        }


def _uncertainty(row: AccuracyRow) -> float:
    if math.isfinite(row.ref_uncertainty):
        return row.ref_uncertainty
    return 0.0 if row.ref_converged else math.inf


def _closest(picks: list[Pick]) -> Pick | None:
    """The smallest error; of several within 1 % of it (the same run on other modes), the
    cheapest."""
    if not picks:
        return None
    smallest = min(p.error for p in picks)
    return min((p for p in picks if p.error <= 1.01 * smallest), key=lambda p: p.cost)


def _groups(picks: list[Pick], key, skip, qualifies) -> list[Group]:
    names = [n for n in dict.fromkeys(key(p) for p in picks) if n != skip]
    out = []
    for name in names:
        mine = [p for p in picks if key(p) == name]
        ok = [p for p in mine if qualifies(p)]
        out.append(Group(name, min(ok, key=lambda p: p.cost) if ok else None, _closest(mine)))
    return out


def predict(picks: list[Pick], max_error: float, time_s: float) -> list[Prediction]:
    """For each line (one variant of one model) still converging at its finest measured dt
    (that row is in its order fit: discretisation, not rounding, dominates there), the dt its
    fitted order says reaches `max_error`, rounded down to a whole number of steps, and its
    cost at the measured cost per step; the cheapest per backend and model, cheapest first.
    None where E is under the reference's uncertainty."""
    out: dict[tuple[str, str], Prediction] = {}  # the cheapest per backend and model
    for label in dict.fromkeys(p.row.label for p in picks):
        finest = min((p for p in picks if p.row.label == label), key=lambda p: p.row.dt)
        order = finest.row.order
        if not (finest.row.in_fit and math.isfinite(order) and order > 0 and finest.bound > max_error):
            continue
        if max_error <= finest.uncertainty:
            continue
        dt = finest.row.dt * ((max_error - finest.uncertainty) / finest.error) ** (1 / order)
        steps = math.ceil(time_s / dt)
        new = Prediction(finest, time_s / steps, steps, finest.row.ms_per_step * steps / time_s)
        key = (finest.row.backend, finest.model)
        if key not in out or new.cost < out[key].cost:
            out[key] = new
    return sorted(out.values(), key=lambda p: p.cost)


def advise(
    run: AccuracyRun,
    setup: Setup,
    max_error: float,
    metric: str = DEFAULT_METRIC,
    backends: set[str] | None = None,
    configure=configuration_for,
) -> Advice:
    """The cheapest configuration of `run` (restricted to `backends`) whose error under
    `metric` stays under `max_error`, with the runners-up; `configure(row, setup)` gives a
    row's runnable Configuration or the reason it has none here."""
    if metric not in METRICS:
        raise ClothbenchError(f"metric must be one of {', '.join(METRICS)}, got {metric!r}")
    column = METRICS[metric]
    picks, left_out = [], {}
    for row in run.rows:
        error = getattr(row, column)
        if backends is not None and row.backend not in backends:
            continue
        if row.status != "ok" or not math.isfinite(error) or not (row.ms_per_sim_s > 0):
            left_out.setdefault(f"{row.label}, dt {row.dt:.4g} s", f"no measurement: {row.status}")
            continue
        config = configure(row, setup)
        if isinstance(config, str):
            left_out[row.label] = config
            continue
        picks.append(Pick(row, config, error, _uncertainty(row)))

    def qualifies(p: Pick) -> bool:
        return p.bound <= max_error

    ok = sorted((p for p in picks if qualifies(p)), key=lambda p: (p.cost, p.error))
    choice = ok[0] if ok else None
    return Advice(
        run,
        metric,
        max_error,
        choice,
        ok[1 : 1 + RUNNERS_UP],
        _groups(picks, lambda p: p.model, choice and choice.model, qualifies),
        _groups(picks, lambda p: p.row.backend, choice and choice.row.backend, qualifies),
        _closest(picks),
        min(picks, key=lambda p: p.cost) if picks else None,
        [] if choice else predict(picks, max_error, run.time_s),
        list(left_out.items()),
    )


__all__ = [
    "METRICS",
    "DEFAULT_METRIC",
    "AccuracyRun",
    "read_accuracy_csv",
    "measured_here",
    "solver_of",
    "check_matches",
    "Configuration",
    "configuration_for",
    "Pick",
    "Prediction",
    "Group",
    "Advice",
    "advise",
    "predict",
]
