"""The OpenCL devices .ci/run reruns the OpenCL tests on, one per runtime not yet covered.

The main run covers this machine's default device; the pip-only leg (Debian's PoCL hidden by the
empty OCL_ICD_VENDORS folder given as argv[1]) covers the default among what pip installs. This
prints two lines: first `all` where the pip-only default is another runtime than the main run's
(the leg runs every OpenCL test), else `choice` (the main run has already run them on that
runtime: the leg runs only the device choice's tests, tests/test_opencl_devices.py, as a pip-only
machine chooses); then, as PYOPENCL_CTX values of the unchanged environment, every compiling
device whose runtime neither default is, so that every runtime that compiles here runs the
OpenCL tests once.
"""

import json
import os
import subprocess
import sys


def devices(env: dict) -> list[dict]:
    # OpenCL's row alone: `clothbench backends --json` probes every peer too, importing each
    # (10 s a call on the Zen 3, 2026-12-06; this one takes 1 s)
    out = subprocess.run(
        ["clothbench", "backends", "opencl", "--json"], capture_output=True, text=True, check=True, env=env
    )
    return next(r for r in json.loads(out.stdout) if r["backend"] == "opencl").get("devices", [])


here = devices(dict(os.environ))
pip_only = devices(dict(os.environ, OCL_ICD_VENDORS=sys.argv[1]))
main_default = {d["runtime"] for d in here if d["default"]}
pip_default = {d["runtime"] for d in pip_only if d["default"]}
print("choice" if pip_default and pip_default == main_default else "all")
print(" ".join(d["device"] for d in here if d["compiles"] and d["runtime"] not in main_default | pip_default))
