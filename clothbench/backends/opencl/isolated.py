"""Work on OpenCL devices in a separate Python process, one device at a time where the first
try dies: a driver's compiler may abort the whole process instead of failing a build (the
PoCL wheel's LLVM 14 did on an AMD EPYC Zen 5, on a float16 square root: docs/opencl-devices.md),
and a process that made such a failed build may abort again at exit. The probe and the
default device's measurement (device.py) run here, so that such a device costs itself, not
the command.

A plain subprocess (`python -m clothbench.backends.opencl.isolated`), not multiprocessing: it
works from inside a harness worker, which is a daemonic process and may not have children of
its own. The call goes in as JSON on stdin, the answers come back as JSON on stdout; the
child's stderr (the drivers' warnings, a compiler's fatal line) stays out of the terminal.
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys

from clothbench.errors import ClothbenchError, signal_name

# Seconds a child may take (building and timing every device takes a few).
TIMEOUT_S = 600.0


def in_child_per_device(target: str, specs: list[str], *args) -> dict:
    """{spec: value} from fn(specs, *args), `target` naming fn as 'module:function', in a child
    process; where that child dies, fn([spec], *args) for each device alone in a child of its
    own, and a ClothbenchError saying what killed it for a device whose child dies too. A
    ClothbenchError that fn returns for a device comes back as one."""
    answers, _ = _child(target, specs, args)
    if answers is not None:
        return answers
    result: dict = {}
    for spec in specs:
        alone, said = _child(target, [spec], args)
        result.update(
            alone
            if alone is not None
            else {
                spec: ClothbenchError(f"OpenCL device {spec}: building clothbench's kernel killed the process ({said})")
            }
        )
    return result


def _child(target: str, specs: list[str], args: tuple) -> tuple[dict | None, str]:
    """(the answers, "") or, where the child died, (None, what killed it)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))  # the caller's modules
    call = json.dumps({"target": target, "specs": specs, "args": list(args)})
    try:
        done = subprocess.run(
            [sys.executable, "-m", __name__], input=call, capture_output=True, text=True, env=env, timeout=TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return None, f"ran past {TIMEOUT_S:g} s and was killed"
    lines = done.stdout.strip().splitlines()
    if done.returncode == 0 and lines:
        encoded = json.loads(lines[-1])
        return {spec: ClothbenchError(a["error"]) if "error" in a else a["value"] for spec, a in encoded.items()}, ""
    fatal = [line.strip() for line in done.stderr.splitlines() if "LLVM ERROR" in line or "error:" in line]
    how = f"exit status {done.returncode}" if done.returncode >= 0 else signal_name(-done.returncode)
    return None, fatal[0] if fatal else f"the child process ended with {how}"


def probe_devices(specs: list[str], source: str) -> dict:
    """In the child: None for each device of `specs` that builds and runs `source`'s
    clothbench_probe, else the compiler's first error (device.compile_error asks)."""
    from clothbench.backends.opencl.build_log import first_error
    from clothbench.backends.opencl.device import build_program, device_context, import_pyopencl

    cl = import_pyopencl()
    result = {}
    for spec in specs:
        p, d = map(int, spec.split(":"))
        dev = cl.get_platforms()[p].get_devices()[d]
        try:
            context = device_context(dev)
            program = build_program(context, source, ())
            try:
                kernel = cl.Kernel(program, "clothbench_probe")
            except cl.Error as e:
                result[spec] = f"its build reported success and left no kernel ({e})"
                continue
            queue = cl.CommandQueue(context, dev)
            data = cl.Buffer(context, cl.mem_flags.READ_WRITE, 16 * 4 * 4)
            kernel(queue, (4,), None, data)
            queue.finish()
            result[spec] = None
        except ClothbenchError as e:
            result[spec] = first_error(str(e))
        except cl.Error as e:
            result[spec] = f"{type(e).__name__}: {e}"
    return result


def main() -> None:
    call = json.loads(sys.stdin.read())
    module, _, name = call["target"].partition(":")
    answers = getattr(importlib.import_module(module), name)(call["specs"], *call["args"])
    encoded = {
        spec: {"error": str(a)} if isinstance(a, ClothbenchError) else {"value": a} for spec, a in answers.items()
    }
    sys.stdout.write(json.dumps(encoded) + "\n")
    sys.stdout.flush()
    os._exit(0)  # not the drivers' exit handlers: one that made a failed build aborts there


if __name__ == "__main__":
    main()
