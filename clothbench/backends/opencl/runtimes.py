"""The OpenCL runtimes (ICDs) a process can see, where each comes from, and making Intel's
CPU runtime from pip (`intel-opencl-rt`) visible with no manual step.

pyopencl's wheel carries its own ICD loader (ocl-icd), which reads the .icd files of
OCL_ICD_VENDORS (a folder, or one file: then only that one) or else /etc/OpenCL/vendors, and
in addition the .icd files beside itself (pyopencl/.libs: the PoCL the wheel bundles) unless
OCL_ICD_VENDORS names a single file. Intel's wheel installs its ICD file under
<prefix>/etc/OpenCL/vendors with a conda placeholder path (/opt/anaconda1anaconda2anaconda3)
that nothing rewrites on a pip install, and its library needs libimf.so and friends from
`intel-cmplr-lib-rt`, in <prefix>/lib, a folder no loader searches.

prepare_loader(), run once before pyopencl's first platform query, therefore: finds Intel's
library through the installed distribution's file list; checks that its dependencies are
beside it, and loads any that is not by path (RTLD_GLOBAL, since LD_LIBRARY_PATH cannot
change once the process runs); writes, under
clothbench's cache, a vendors folder holding an ICD file with the library's real path plus
copies of the .icd files the loader would have read anyway; and points OCL_ICD_VENDORS at it
for the one moment the loader reads it (its first platform query), so that the environment
a run records is the one its user gave. Nothing is done when the runtime is not installed or
an ICD file the loader reads already names it. docs/opencl-devices.md has the whole story.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from clothbench.native import cache_dir

INTEL_DISTRIBUTION = "intel-opencl-rt"
INTEL_LIBRARY = "libintelocl.so"
INTEL_EXTRA = "pip install 'clothbench[intel-opencl]'"
SYSTEM_VENDORS = "/etc/OpenCL/vendors"  # ocl-icd's built-in folder (OPENCL_VENDOR_PATH overrides it)

# What libintelocl.so needs beyond the system's libraries, each after the ones it needs
# (libintlc.so is a linker script naming libintlc.so.5; only the latter loads).
INTEL_DEPENDENCIES = (
    ("libintlc.so.5", "intel-cmplr-lib-rt"),
    ("libirng.so", "intel-cmplr-lib-rt"),
    ("libimf.so", "intel-cmplr-lib-rt"),
    ("libsvml.so", "intel-cmplr-lib-rt"),
    ("libtbb.so.12", "tbb"),
)


@dataclass(frozen=True)
class IntelRuntime:
    """What prepare_loader() found and did about Intel's pip runtime."""

    library: str = ""  # real path of libintelocl.so, "" when the distribution is absent
    icd_file: str = ""  # the ICD file clothbench wrote, "" when it wrote none
    note: str = ""  # one line: why it is or is not visible


_prepared: IntelRuntime | None = None


def intel_runtime() -> IntelRuntime:
    """What prepare_loader() did (it runs at the first OpenCL import)."""
    return _prepared if _prepared is not None else IntelRuntime(note="OpenCL not imported yet")


def prepare_loader(cl) -> IntelRuntime:
    """Once per process, before the ICD loader first reads its vendors (pyopencl imported as
    `cl`): make Intel's pip runtime one of the loader's ICDs where it is installed."""
    global _prepared
    if _prepared is None:
        _prepared = _prepare(cl)
    return _prepared


def _prepare(cl) -> IntelRuntime:
    library = _distribution_file(INTEL_DISTRIBUTION, INTEL_LIBRARY)
    if library is None:
        return IntelRuntime(note=f"Intel's CPU runtime is not installed ({INTEL_EXTRA})")
    library = os.path.realpath(library)
    already = [icd for icd in loader_icd_files() if _names_intel(icd)]
    if already:
        return IntelRuntime(library, note=f"Intel's CPU runtime is registered by {already[0]}")
    missing = preload_dependencies(Path(library).parent)
    if missing:
        return IntelRuntime(library, note=f"Intel's CPU runtime lacks {', '.join(missing)} ({INTEL_EXTRA})")
    folder = vendors_folder(library, loader_icd_files())
    given = os.environ.get("OCL_ICD_VENDORS")
    os.environ["OCL_ICD_VENDORS"] = str(folder)
    try:
        # the loader reads its vendors now, once for the process (pyopencl's own binding:
        # a test's stand-in for cl.get_platforms must not leave the loader unread)
        getattr(cl, "_cl", cl).get_platforms()
    except cl.Error:  # no platform at all: the caller says so with its own hint
        pass
    finally:
        if given is None:
            del os.environ["OCL_ICD_VENDORS"]
        else:
            os.environ["OCL_ICD_VENDORS"] = given
    return IntelRuntime(library, str(folder / "intel-cpu.icd"), note="Intel's CPU runtime from pip")


def _distribution_file(distribution: str, name: str) -> str | None:
    """Where the installed `distribution` put its file called `name`, if it is installed."""
    try:
        files = metadata.distribution(distribution).files or ()
    except metadata.PackageNotFoundError:
        return None
    for f in files:
        if f.name == name:
            path = os.path.normpath(str(f.locate()))
            if os.path.exists(path):
                return path
    return None


def preload_dependencies(beside: Path) -> list[str]:
    """Make each of INTEL_DEPENDENCIES loadable for libintelocl.so: those in the folder
    `beside` (a pip install puts them there) its own RUNPATH ($ORIGIN) finds; any other is
    loaded by path from where its distribution put it, into the global namespace, where the
    library's load finds it. Only those: libimf.so also defines exp, log, pow, ... (libm,
    loaded first, still wins for any library loaded later, but nothing is gained by
    widening that). Returns the libraries not found, each with the distribution that has it."""
    missing = []
    for name, distribution in INTEL_DEPENDENCIES:
        if (beside / name).exists():
            continue
        path = _distribution_file(distribution, name)
        if path is None:
            missing.append(f"{name} (from {distribution})")
            continue
        try:
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        except OSError as e:
            missing.append(f"{name} ({e})")
    return missing


def loader_icd_files() -> list[Path]:
    """The .icd files the ICD loader reads, as the environment stands (ocl-icd's rules)."""
    given = os.environ.get("OCL_ICD_VENDORS")
    if given:
        path = Path(given)
        if path.is_file():
            return [path]
        folder = path
    else:
        folder = Path(os.environ.get("OPENCL_VENDOR_PATH") or SYSTEM_VENDORS)
    try:
        return sorted(p for p in folder.iterdir() if p.suffix == ".icd" and p.is_file())
    except OSError:
        return []


def _names_intel(icd: Path) -> bool:
    """Whether an ICD file names a libintelocl that can load: a bare name (found on the
    library path) or a path that exists; the pip wheel's placeholder path does not."""
    try:
        line = icd.read_text().strip()
    except OSError:
        return False
    return Path(line).name.startswith("libintelocl") and ("/" not in line or os.path.exists(line))


def vendors_folder(library: str, icds: list[Path]) -> Path:
    """A folder in clothbench's cache holding intel-cpu.icd (naming `library`) and a copy of
    each of `icds`; one folder per content, so that processes never rewrite each other's."""
    contents = {"intel-cpu.icd": library + "\n"}
    for icd in icds:
        try:
            text = icd.read_text()
        except OSError:
            continue
        name = icd.name if icd.name not in contents else f"system-{icd.name}"
        contents[name] = text
    digest = hashlib.sha256(repr(sorted(contents.items())).encode()).hexdigest()[:16]
    folder = cache_dir("opencl-vendors", digest)
    for name, text in contents.items():
        path = folder / name
        if not path.exists() or path.read_text() != text:
            partial = folder / f".{name}.{os.getpid()}.partial"
            partial.write_text(text)
            os.replace(partial, path)  # atomic: a loader never reads half a file
    return folder


# --- where a platform comes from -------------------------------------------------------------

SYSTEM_POCL, INTEL_CPU, OTHER, WHEEL_POCL = "system PoCL", "Intel CPU runtime", "other", "PoCL wheel"
# The default device's order where it is not measured: what measured fastest on both CPUs
# seen (docs/opencl-devices.md), a vendor's other driver (a GPU's, say) before the wheel.
RUNTIME_ORDER = (SYSTEM_POCL, INTEL_CPU, OTHER, WHEEL_POCL)

_wheel_platforms: set[int] | None = None


def runtime_of(platform) -> str:
    """Which of RUNTIME_ORDER a pyopencl platform is."""
    if platform.int_ptr in wheel_platform_ids():
        return WHEEL_POCL
    name = platform.name
    if "Portable Computing Language" in name or "PoCL" in platform.version:
        return SYSTEM_POCL
    if name.startswith("Intel(R) OpenCL") and "Graphics" not in name:
        return INTEL_CPU
    return OTHER


def wheel_platform_ids() -> set[int]:
    """The platform ids of the ICDs that pyopencl's wheel bundles (the .icd files beside its
    loader, naming libraries in that folder), asked of each library itself: a PoCL is told
    from another PoCL by the library that made it, not by a version string."""
    global _wheel_platforms
    if _wheel_platforms is None:
        import pyopencl

        _wheel_platforms = set()
        libs = Path(pyopencl.__file__).parent / ".libs"
        for icd in sorted(libs.glob("*.icd")) if libs.is_dir() else ():
            library = libs / icd.read_text().strip()
            if library.exists() and _is_loaded(library):
                _wheel_platforms |= set(library_platform_ids(str(library)))
    return _wheel_platforms


def _is_loaded(library: Path) -> bool:
    """Whether the process has mapped `library` (the loader loads each ICD it reads): asking
    one that is not loaded would load ~100 MB for nothing."""
    real = os.path.realpath(library)
    try:
        with open("/proc/self/maps") as maps:
            return any(line.rstrip().endswith(real) or line.rstrip().endswith(str(library)) for line in maps)
    except OSError:
        return True


def library_platform_ids(library: str) -> list[int]:
    """The platform ids an ICD library reports through clIcdGetPlatformIDsKHR, the entry
    point every ICD has (the loader calls the same): the loader hands them on unchanged, so
    they are pyopencl's Platform.int_ptr."""
    try:
        lib = ctypes.CDLL(library)
        lookup = lib.clGetExtensionFunctionAddress
    except (OSError, AttributeError):
        return []
    lookup.restype, lookup.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
    address = lookup(b"clIcdGetPlatformIDsKHR")
    if not address:
        return []
    uint_p, ids_p = ctypes.POINTER(ctypes.c_uint), ctypes.POINTER(ctypes.c_void_p)
    get_ids = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_uint, ids_p, uint_p)(address)
    count = ctypes.c_uint()
    if get_ids(0, None, ctypes.byref(count)) != 0 or not count.value:
        return []
    ids = (ctypes.c_void_p * count.value)()
    if get_ids(count.value, ids, None) != 0:
        return []
    return [i for i in ids if i]
