"""The compiler's log of a failed OpenCL build, the same way on every runtime.

Where pyopencl puts the log depends on the runtime (measured, docs/opencl-devices.md):
on PoCL it builds the program object itself, and the log is both in that program's build
info and in the exception; on any other runtime (Intel's) it builds a second program of
its own for its binary cache, so the program we hold was never built (its log is empty,
and asking for it makes pyopencl warn) and the log is only in the exception's text, one
"Build on <device>:" section per device. So the exception's text is what is read.
"""

from __future__ import annotations

import re

# "Build on <pyopencl.Device ...>:\n\n<log>", ended by the next device's section (75 '='),
# or the options and saved-source notes pyopencl appends, or the end
_SECTION = re.compile(r"^Build on <[^\n]*>:\n\n(.*?)(?=={75}|^\(options: |^\(source saved as |\Z)", re.M | re.S)

# Lines that say nothing about the error: Intel's progress lines (in its log on every build)
# and clang's error count (PoCL's compiler prints it to the process's stderr, not the log)
_NOISE = re.compile(
    r"^(Compilation (started|done|failed)|Linking (started|done|failed)|Device build (started|done)"
    r"|\d+ (error|warning)s? generated\.?)$"
)

# A compiler diagnostic with its place: PoCL writes "error: file:line:col: message", Intel's
# compiler (clang's default) "file:line:col: error: message"
_PLACED = re.compile(r"^(?:(?:fatal )?error: (.+?):(\d+):\d+: (.*)|(.+?):(\d+):\d+: (?:fatal )?error: (.*))$")


def compiler_log(error_text: str) -> str:
    """The log of the failed build whose exception says `error_text`: its per-device
    sections (else all of it), the runtimes' progress lines left out."""
    sections = [s.strip() for s in _SECTION.findall(error_text)]
    log = "\n".join(s for s in sections if s) or error_text.strip()
    return "\n".join(line for line in log.splitlines() if not _NOISE.match(line.strip())).strip()


def error_places(message: str) -> list[tuple[str, int, str]]:
    """(file, line, message) of every placed compiler error in `message`, either runtime's form."""
    found = []
    for line in message.splitlines():
        placed = _PLACED.match(line.strip())
        if placed:
            g = placed.groups()
            found.append((g[0], int(g[1]), g[2]) if g[0] else (g[3], int(g[4]), g[5]))
    return found


def first_error(message: str) -> str:
    """The compiler's first error in `message`, without its file and line; else the first
    line starting "error:" without that, else the last line."""
    places = error_places(message)
    if places:
        return places[0][2].strip()
    lines = [line.strip() for line in message.splitlines() if line.strip()]
    for line in lines:
        if line.startswith("error:"):
            return line.partition("error:")[2].strip()
    return lines[-1] if lines else "?"
