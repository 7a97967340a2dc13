"""Every OpenCL device and which is the default (clothbench/backends/opencl/device.py), and
Intel's pip runtime made visible (runtimes.py): the listing names every device pyopencl
sees; the default follows the stated rule (measured and cached, or with CLOTHBENCH_TUNING=off
the order system PoCL, Intel, other, PoCL wheel); a pip-only machine works or says the one
command that fixes it; the ICD file clothbench writes names a library that exists; strict is
bit-exact with NumPy float32 on every runtime that compiles; a row says which runtime ran it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.cli import main
from clothbench.errors import ClothbenchError
from clothbench.harness import reference, simulate

from conftest import VERLET, assert_bit_exact, require, sphere

ROOT = Path(__file__).resolve().parent.parent
device = pytest.importorskip("clothbench.backends.opencl.device")
runtimes = device.runtimes


# --- fakes: a machine's platforms, without its drivers -------------------------------------


class FakeDevice:
    def __init__(self, name, platform, ptr):
        self.name, self.platform, self.int_ptr = name, platform, ptr
        self.driver_version, self.version = platform.driver, f"OpenCL 3.0 {name}"


class FakePlatform:
    def __init__(self, name, version, driver, ptr):
        self.name, self.version, self.driver, self.int_ptr = name, version, driver, ptr
        self.devices = [FakeDevice(f"cpu of {driver}", self, ptr + 1)]

    def get_devices(self):
        return self.devices


WHEEL = FakePlatform("Portable Computing Language", "OpenCL 3.0 PoCL 3.0-rc2 Linux, LLVM 14.0.6", "3.0-rc2", 100)
INTEL = FakePlatform("Intel(R) OpenCL", "OpenCL 3.1 LINUX", "2026.22", 200)
DEBIAN = FakePlatform("Portable Computing Language", "OpenCL 3.0 PoCL 3.1+debian Linux, LLVM 15.0.6", "3.1+debian", 300)


@pytest.fixture
def machine(monkeypatch, tmp_path):
    """Install fake platforms (listed as given, the wheel's PoCL known by its id) and which
    of their devices compile; a fresh default-device cache and tuning folder."""
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(device, "_defaults", {})
    monkeypatch.setattr(device, "_retuned", False)
    monkeypatch.setattr(runtimes, "_wheel_platforms", {WHEEL.int_ptr})

    def install(platforms, failing=()):
        monkeypatch.setattr(device, "_platforms", lambda: list(platforms))
        errors = {p.devices[0].int_ptr: "unknown target CPU 'generic'" for p in failing}
        monkeypatch.setattr(device, "compile_error", lambda dev: errors.get(dev.int_ptr))

    return install


def test_runtime_kinds_tell_the_wheels_pocl_from_the_systems(machine):
    assert [runtimes.runtime_of(p) for p in (WHEEL, INTEL, DEBIAN)] == [
        runtimes.WHEEL_POCL,
        runtimes.INTEL_CPU,
        runtimes.SYSTEM_POCL,
    ]


def test_default_with_tuning_off_is_the_first_that_compiles_in_the_stated_order(machine):
    machine([WHEEL, INTEL, DEBIAN])  # listed in the opposite order on purpose
    chosen = device.default_device()
    assert (chosen.spec, chosen.device) == ("2:0", DEBIAN.devices[0])
    assert "CLOTHBENCH_TUNING=off" in chosen.reason and "system PoCL, Intel CPU runtime" in chosen.reason

    machine([WHEEL, INTEL, DEBIAN], failing=[DEBIAN])
    device._defaults.clear()
    assert device.default_device().spec == "1:0", "Intel's runtime before the PoCL wheel"

    machine([WHEEL, INTEL, DEBIAN], failing=[DEBIAN, INTEL])
    device._defaults.clear()
    only = device.default_device()
    assert only.spec == "0:0" and only.reason == "the only OpenCL device here that compiles"


def test_default_with_tuning_on_is_the_fastest_measured_once_and_kept(machine, monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    machine([DEBIAN, INTEL, WHEEL])
    timings = {"0:0": 0.9e-3, "1:0": 0.4e-3, "2:0": 0.7e-3}  # seconds per step
    asked = []

    def seconds_per_step(specs):
        asked.append(specs)
        return {s: timings[s] for s in specs}

    monkeypatch.setattr(device, "isolated_seconds_per_step", seconds_per_step)
    chosen = device.default_device()
    assert chosen.spec == "1:0" and asked == [["0:0", "1:0", "2:0"]], "all devices timed together, once"
    assert "fastest of 3" in chosen.reason and "1:0 0.40" in chosen.reason, chosen.reason

    device._defaults.clear()  # a new process: the choice comes from the tuning file
    assert device.default_device().spec == "1:0" and len(asked) == 1
    timings["0:0"] = 0.1e-3  # a new driver build is faster: --retune sees it, once per process
    assert device.default_device(retune=True).spec == "0:0" and len(asked) == 2
    assert device.default_device(retune=True).spec == "0:0" and len(asked) == 2


def test_a_near_tie_goes_to_the_earlier_runtime_in_the_stated_order(machine, monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    machine([WHEEL, DEBIAN])  # the wheel listed first and 5% faster: noise, not a reason
    timed = {"0:0": 0.95e-3, "1:0": 1.0e-3}
    monkeypatch.setattr(device, "isolated_seconds_per_step", lambda specs: timed)
    assert device.default_device().spec == "1:0"
    timed["0:0"] = 0.5e-3
    assert device.default_device(retune=True).spec == "0:0", "a clear win is a win"


def test_a_device_that_fails_to_build_the_step_is_not_the_default(machine, monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    machine([DEBIAN, INTEL])
    timed = {"0:0": ClothbenchError("build failed"), "1:0": 1e-3}
    monkeypatch.setattr(device, "isolated_seconds_per_step", lambda specs: timed)
    assert device.default_device().spec == "1:0"


def test_no_device_that_compiles_names_the_one_command_that_fixes_it(machine):
    machine([WHEEL], failing=[WHEEL])  # the PoCL wheel on a CPU newer than its LLVM (AMD Zen 5)
    with pytest.raises(ClothbenchError) as e:
        device.default_device()
    message = str(e.value)
    assert "\n" not in message and "unknown target CPU" in message
    assert message.endswith(f"this PoCL's LLVM predates the CPU: {device.FIX_HINT}")
    assert device.FIX_HINT.startswith("pip install 'clothbench[intel-opencl]'")


def test_the_fix_hints_extra_installs_intels_runtime_and_its_libraries():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    names = {r.split(">")[0].split("=")[0].split("[")[0].strip() for r in extras["intel-opencl"]}
    assert runtimes.INTEL_DISTRIBUTION in names
    assert {dist for _, dist in runtimes.INTEL_DEPENDENCIES} <= names


def test_pyopencl_ctx_wins_over_the_default_in_the_listing(machine, monkeypatch):
    machine([DEBIAN, INTEL])
    monkeypatch.setenv("PYOPENCL_CTX", "1:0")
    monkeypatch.setattr(device, "choose_device", lambda spec, retune=False: INTEL.devices[0])
    rows, line = device.device_listing()
    assert [r["default"] for r in rows] == [False, True]
    assert line.startswith("default: 1:0 cpu of 2026.22 (Intel CPU runtime): PYOPENCL_CTX=1:0")
    assert [r["llvm"] for r in rows] == ["15.0.6", ""], "the LLVM where the version string names one"


# --- the real machine ---------------------------------------------------------------------


def test_listing_names_every_device_pyopencl_sees_with_its_driver_version(capsys, monkeypatch):
    require("opencl")
    monkeypatch.setenv("COLUMNS", "300")  # rich wraps a captured table at 80 otherwise
    cl = device.import_pyopencl()
    seen = [(d.name, d.driver_version, p.name) for p in cl.get_platforms() for d in p.get_devices()]
    assert main(["backends", "--json"]) == 0
    row = next(r for r in json.loads(capsys.readouterr().out) if r["backend"] == "opencl")
    assert [(d["name"], d["driver_version"], d["platform"]) for d in row["devices"]] == seen
    assert sum(d["default"] for d in row["devices"]) == 1
    default = next(d for d in row["devices"] if d["default"])
    assert default["compiles"] and default["name"] == row["device"]
    assert row["default_device"].startswith(f"default: {default['device']} {default['name']} (")
    # the opencl row names the default's runtime too: its device name is the CPU's under Intel's
    assert row["driver"] == f"{default['platform']}: {default['platform_version']}; driver {default['driver_version']}"

    assert main(["backends"]) == 0
    out = capsys.readouterr().out
    assert "OpenCL devices" in out and "\ndefault: " in out
    for name, version, _ in seen:
        assert version in out


def test_measured_default_on_the_real_devices_is_kept_and_never_recurses(monkeypatch, tmp_path):
    # the backends built to time each device name it explicitly: choosing the default never
    # asks for the default again (choose_device is also called by every backend's queue)
    require("opencl")
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    monkeypatch.setattr(device, "_defaults", {})
    picks, real_pick = [], device._pick_default
    monkeypatch.setattr(device, "_pick_default", lambda *a: picks.append(a) or real_pick(*a))
    chosen = device.default_device()
    compiling = [spec for spec, dev, _ in device.ordered_devices() if device.compile_error(dev) is None]
    assert len(picks) == 1 and chosen.spec in compiling
    if len(compiling) > 1:
        kept = json.loads((tmp_path / "tuning" / f"{device.DEFAULT_TUNING}.json").read_text())
        (entry,) = kept.values()
        assert len(entry["ms"]) + len(entry["failed"]) == len(compiling) and entry["choice"] in entry["ms"]


def _compiler_aborts_on_1_0(specs: list[str]) -> dict:
    """A stand-in for the default device's measurement (module level: the child process imports
    it) on which device 1:0's compiler aborts the process, as the PoCL wheel's LLVM 14 did on a
    Zen 5 building the fast Verlet kernel."""
    if "1:0" in specs:
        sys.stderr.write("LLVM ERROR: Cannot select: 0x1: i64 = fsqrt 0x2\n")
        sys.stderr.flush()
        os.abort()
    return {spec: 0.001 for spec in specs}


def test_a_device_whose_compiler_aborts_the_process_costs_that_device_not_the_command():
    # measured in a child, then, when the child dies, each device alone in a child of its own:
    # the others keep their times and the culprit is failed with its compiler's fatal line
    got = device.isolated_seconds_per_step(["0:0", "1:0", "2:0"], measure=f"{__name__}:_compiler_aborts_on_1_0")
    assert got["0:0"] == got["2:0"] == 0.001
    assert isinstance(got["1:0"], ClothbenchError), got
    assert "1:0" in str(got["1:0"]) and "LLVM ERROR: Cannot select" in str(got["1:0"]), got["1:0"]


def test_a_device_named_by_hand_that_fails_the_probe_is_refused_before_any_build(monkeypatch):
    # --device 2:0 on the Zen 5 named the wheel whose compiler aborted the process: the probe's
    # answer refuses it in one line instead
    require("opencl")
    monkeypatch.setattr(device, "compile_error", lambda dev: "its build reported success and left no kernel")
    refused = r"^OpenCL device 0:0 \(.+\) cannot compile clothbench's kernels: its build"
    with pytest.raises(ClothbenchError, match=refused):
        create_backend("opencl", sphere(8), VERLET, BackendOptions(device="0:0"))


def test_empty_vendors_folder_sees_only_pip_runtimes_and_works_or_says_the_fix(tmp_path):
    # OCL_ICD_VENDORS=<empty folder>: what a pip-only machine sees (the PoCL wheel, Intel's
    # runtime where the extra is installed). In a child: the loader reads its vendors once.
    require("opencl")
    empty = tmp_path / "vendors"
    empty.mkdir()
    env = {**os.environ, "OCL_ICD_VENDORS": str(empty)}
    env.pop("PYOPENCL_CTX", None)
    done = subprocess.run(
        [sys.executable, "-m", "clothbench", "backends", "opencl", "--json"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    row = next(r for r in json.loads(done.stdout) if r["backend"] == "opencl")
    if row["usable"]:
        assert {d["runtime"] for d in row["devices"]} <= {runtimes.WHEEL_POCL, runtimes.INTEL_CPU}
        assert any(d["default"] and d["compiles"] for d in row["devices"])
    else:
        assert "\n" not in row["reason"] and device.FIX_HINT in row["reason"], row["reason"]


def test_intels_icd_file_names_a_library_that_exists():
    require("opencl")
    intel = runtimes.intel_runtime()
    if not intel.library:
        pytest.skip(intel.note)
    if not intel.icd_file:  # an ICD the loader reads already names it
        assert "registered by" in intel.note, intel.note
        return
    named = Path(Path(intel.icd_file).read_text().strip())
    assert named.is_absolute() and named.name.startswith("libintelocl") and named.exists()
    platforms = [p.name for p in device.import_pyopencl().get_platforms()]
    assert "Intel(R) OpenCL" in platforms, "the written ICD made Intel's runtime visible"


def test_vendors_folder_holds_intels_icd_and_the_loaders_own(tmp_path, monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path / "cache"))
    system = tmp_path / "system"
    system.mkdir()
    (system / "pocl.icd").write_text("libpocl.so.2\n")
    (system / "intel-cpu.icd").write_text("/opt/anaconda1anaconda2anaconda3/lib/libintelocl.so\n")
    (system / "readme.txt").write_text("not an ICD")
    monkeypatch.setenv("OCL_ICD_VENDORS", str(system))
    icds = runtimes.loader_icd_files()
    assert [p.name for p in icds] == ["intel-cpu.icd", "pocl.icd"]
    assert not any(runtimes._names_intel(p) for p in icds), "the placeholder path is not usable"
    folder = runtimes.vendors_folder("/real/lib/libintelocl.so", icds)
    files = {p.name: p.read_text() for p in folder.iterdir()}
    assert files == {
        "intel-cpu.icd": "/real/lib/libintelocl.so\n",
        "system-intel-cpu.icd": "/opt/anaconda1anaconda2anaconda3/lib/libintelocl.so\n",
        "pocl.icd": "libpocl.so.2\n",
    }
    assert runtimes.vendors_folder("/real/lib/libintelocl.so", icds) == folder, "one folder per content"
    monkeypatch.setenv("OCL_ICD_VENDORS", str(system / "pocl.icd"))  # a file: the loader reads only it
    assert runtimes.loader_icd_files() == [system / "pocl.icd"]


def test_intels_runtime_without_its_libraries_says_what_to_install(tmp_path, monkeypatch):
    # pip install intel-opencl-rt alone leaves out libimf.so & co (intel-cmplr-lib-rt): the
    # loader would skip its ICD in silence
    monkeypatch.setattr(runtimes, "_distribution_file", lambda distribution, name: None)
    missing = runtimes.preload_dependencies(tmp_path)
    assert "libimf.so (from intel-cmplr-lib-rt)" in missing and "libtbb.so.12 (from tbb)" in missing


def _device_of(runtime: str) -> str:
    """The 'platform:device' of the first device of `runtime` that compiles, or skip."""
    require("opencl")
    for spec, dev, kind in device.ordered_devices():
        if kind == runtime:
            error = device.compile_error(dev)
            if error is None:
                return spec
            pytest.skip(f"{runtime} here cannot compile: {error}")
    why = f" ({runtimes.intel_runtime().note})" if runtime == runtimes.INTEL_CPU else ""
    pytest.skip(f"no {runtime} here{why}")


RUNTIMES = (runtimes.SYSTEM_POCL, runtimes.INTEL_CPU, runtimes.WHEEL_POCL)
# a test that picks each runtime's device itself gives the same answer whichever is the default:
# .ci/run runs it with the full tier, not again in each runtime's leg
EVERY_RUNTIME = pytest.mark.every_runtime


@EVERY_RUNTIME
@pytest.mark.parametrize("generic", [False, True], ids=["specialised", "generic"])
@pytest.mark.parametrize("n", [32, 64])
@pytest.mark.parametrize("scene_name", ["sphere", "drape"])
@pytest.mark.parametrize("runtime", RUNTIMES)
def test_strict_is_bit_exact_on_every_runtime_that_compiles(runtime, scene_name, n, generic):
    from clothbench.model.scene import load_scene

    spec = _device_of(runtime)
    scene, steps = load_scene(scene_name).replace(grid=n), 500  # 500: after contact
    pos, prev = simulate("opencl", scene, VERLET, steps, BackendOptions(strict=True, generic=generic, device=spec))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    what = f"{runtime} ({spec}) {scene_name} n={n} generic={generic}"
    assert_bit_exact(pos, ref_pos, f"pos, {what}")
    assert_bit_exact(prev, ref_prev, f"prev, {what}")


@EVERY_RUNTIME
@pytest.mark.parametrize("runtime", RUNTIMES)
def test_driver_names_the_platform_and_its_versions(runtime):
    spec = _device_of(runtime)
    with create_backend("opencl", sphere(8), VERLET, BackendOptions(device=spec)) as b:
        platform = b._device.platform
        assert b.driver.startswith(f"{platform.name}: {' '.join(platform.version.split())}")
        assert b.driver.endswith(f"driver {b._device.driver_version}")


def _pyopencl_driver(spec: str) -> tuple[str, str, str]:
    """(platform name, platform version, device driver version) of the device `spec` names,
    as pyopencl itself answers: what a run on that context must print."""
    p, d = map(int, spec.split(":"))
    platform = device.import_pyopencl().get_platforms()[p]
    return platform.name, " ".join(platform.version.split()), platform.get_devices()[d].driver_version


@EVERY_RUNTIME
@pytest.mark.parametrize("runtime", RUNTIMES)
def test_run_prints_the_opencl_platform_and_driver_version_of_its_context(runtime, monkeypatch, capsys):
    # every runtime's device here is "... Intel(R) Xeon(R) Processor": the driver line says which ran
    spec = _device_of(runtime)
    monkeypatch.setenv("PYOPENCL_CTX", spec)
    monkeypatch.setenv("COLUMNS", "400")  # rich wraps a captured table at 80 otherwise
    assert main(["run", "--backend", "opencl", "--grid", "8", "--steps", "2"]) == 0
    printed = {
        cells[1].strip(): cells[2].strip()
        for line in capsys.readouterr().out.splitlines()
        if len(cells := line.split("│")) == 4
    }
    name, version, driver = _pyopencl_driver(spec)
    assert printed["driver"] == f"{name}: {version}; driver {driver}", printed


@EVERY_RUNTIME
def test_run_names_two_opencl_runtimes_apart_by_their_drivers(capsys):
    require("opencl")
    first = {}  # runtime -> the first device of it that compiles
    for spec, dev, kind in device.ordered_devices():
        if device.compile_error(dev) is None:
            first.setdefault(kind, spec)
    if len(first) < 2:
        pytest.skip(f"one OpenCL runtime here compiles ({', '.join(first) or 'none'}): nothing to tell apart")
    drivers = []
    for spec in list(first.values())[:2]:
        assert main(["run", "--backend", "opencl", "--device", spec, "--grid", "8", "--steps", "2", "--json"]) == 0
        ran = json.loads(capsys.readouterr().out)
        name, version, driver = _pyopencl_driver(spec)
        assert ran["driver"] == f"{name}: {version}; driver {driver}", (spec, ran["driver"])
        drivers.append(ran["driver"])
    assert drivers[0] != drivers[1], f"{list(first)[:2]} both say {drivers[0]!r}"


# --- a build error names the file, the line and the compiler's error on every runtime ------

# The exceptions pyopencl 2026.1 raised for one failed build (file names from #line marks),
# trimmed: PoCL's log is also the program's own, Intel's only the exception's (build_log.py)
POCL_FAILURE = """clBuildProgram failed: BUILD_PROGRAM_FAILURE - clBuildProgram failed: BUILD_PROGRAM_FAILURE

Build on <pyopencl.Device 'pthread-haswell-AMD EPYC' on 'Portable Computing Language' at 0x5>:

error: foo.cl:3:14: expected ';' after expression
error: bar.cl:40:41: use of undeclared identifier 'undefined_x'
Device pthread-haswell-AMD EPYC failed to build the program

(options: -I /site-packages/pyopencl/cl)"""
INTEL_FAILURE = """clBuildProgram failed: BUILD_PROGRAM_FAILURE - clBuildProgram failed: BUILD_PROGRAM_FAILURE

Build on <pyopencl.Device 'AMD EPYC' on 'Intel(R) OpenCL' at 0x5>:

Compilation started
foo.cl:3:14: error: expected ';' after expression
    3 |   a[0] = 1.0f
      |              ^
bar.cl:40:41: error: use of undeclared identifier 'undefined_x'
Compilation failed

(options: -I /site-packages/pyopencl/cl)
(source saved as /tmp/tmpvmiy32wp.cl)"""


@pytest.mark.parametrize("text", [POCL_FAILURE, INTEL_FAILURE], ids=["pocl", "intel"])
def test_the_build_log_is_read_from_either_runtimes_exception(text):
    from clothbench.backends.opencl.build_log import compiler_log, error_places, first_error

    log = compiler_log(text)
    assert "Build on" not in log and "clBuildProgram" not in log and "(options:" not in log, log
    assert "Compilation" not in log and "source saved" not in log, log
    assert error_places(log) == [
        ("foo.cl", 3, "expected ';' after expression"),
        ("bar.cl", 40, "use of undeclared identifier 'undefined_x'"),
    ]
    assert first_error(text) == "expected ';' after expression"


# (the kernel file, a file it includes that this build compiles, what builds it): the
# includes sit inside conditionals (collide.cl, fast_math.cl, <mesh_colliders>) that a
# build skips in part, and the lines after a skipped one must still be named right
BROKEN_BUILDS = {
    "verlet": (
        "verlet_cloth.cl",
        "fast_math.cl",
        lambda spec: (sphere(8), VERLET, BackendOptions(strict=True, device=spec)),
    ),
    "verlet-generic": (
        "verlet_cloth.cl",
        "collide.cl",
        lambda spec: (sphere(8), VERLET, BackendOptions(strict=True, generic=True, device=spec)),
    ),
    "pbd": ("pbd_cloth.cl", "collide.cl", lambda spec: (*_pbd_curtain(), BackendOptions(strict=True, device=spec))),
}


def _pbd_curtain():
    from conftest import setup

    s = setup("curtain", 16).replace(solver="pbd", method="jacobi", iterations=4)
    return s.scene, s.solver


@EVERY_RUNTIME
@pytest.mark.parametrize("build", BROKEN_BUILDS)
@pytest.mark.parametrize("runtime", RUNTIMES)
def test_a_broken_kernel_names_file_line_and_error_on_every_runtime(runtime, build, monkeypatch):
    # an error at the end of the kernel file and one at the end of a file it includes: each
    # named at its own line through the #line marks, whichever runtime compiles (and wherever
    # it keeps the log)
    from clothbench import kernel_source
    from clothbench.backends.opencl.build_log import error_places

    spec = _device_of(runtime)
    filename, included, arguments = BROKEN_BUILDS[build]
    real = kernel_source.read_kernel
    broken = {filename: "float broken(void) { return no_such_value; }", included: "no_such_type broken_too;"}
    edited = {name: f"{real(name)}\n{line}\n" for name, line in broken.items()}
    monkeypatch.setattr(kernel_source, "read_kernel", lambda name: edited.get(name) or real(name))
    monkeypatch.setattr(device, "read_kernel", lambda name: edited.get(name) or real(name))
    with pytest.raises(ClothbenchError) as e:
        create_backend("opencl", *arguments(spec))
    message = str(e.value)
    assert message.startswith("OpenCL build failed on "), message
    places = error_places(message)
    errors = {filename: "use of undeclared identifier 'no_such_value'", included: "unknown type name 'no_such_type'"}
    for name, line in broken.items():
        number = edited[name].splitlines().index(line) + 1
        assert (name, number, errors[name]) in places, f"{runtime} ({spec}) {build}: {message}"
