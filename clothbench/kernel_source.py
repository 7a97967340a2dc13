"""Finding the kernel sources in kernels/, from a checkout or from an installed wheel, with
their includes resolved, and writing exact float literals into them.

The wheel carries kernels/ as clothbench/kernels (see pyproject.toml); a checkout or an
editable install reads the top-level kernels/ folder beside the package.
"""

from __future__ import annotations

import hashlib
import re
from importlib import resources
from pathlib import Path
from typing import Callable

import numpy as np

from clothbench.errors import ClothbenchError

_REPO_KERNELS = Path(__file__).resolve().parent.parent / "kernels"


def kernel_path(filename: str) -> Path:
    installed = Path(str(resources.files("clothbench") / "kernels" / filename))
    for path in (installed, _REPO_KERNELS / filename):
        if path.is_file():
            return path
    raise ClothbenchError(
        f"kernel source {filename} not found (looked in {installed.parent} and {_REPO_KERNELS}); reinstall clothbench"
    )


def read_kernel(filename: str) -> str:
    return kernel_path(filename).read_text()


_INCLUDE = re.compile(r'^[ \t]*#include[ \t]+(?:"([^"]+)"|<([^>]+)>)[ \t]*(?://.*)?$', re.M)
# a conditional directive, with any continuation lines
_CONDITIONAL = re.compile(r"^[ \t]*#[ \t]*(if|ifdef|ifndef|elif|else|endif)\b(?:[^\n]*\\\n)*[^\n]*$", re.M)


def resolve_includes(
    filename: str,
    text: str,
    line_mark: Callable[[int, int, str], str],
    generated: dict[str, Callable[[], str]] | None = None,
) -> tuple[str, list[str]]:
    """`text` (kernels/`filename`) with its includes resolved on the host: `#include "file"` is
    kernels/file (itself resolved), `#include <name>` the source generated[name]() returns.
    line_mark(line, file number, file name) is the `#line` directive put at the start of each
    file and after each include, so that a compiler message gives the line of the file it is
    in. Returns the source and the names of its files, numbered in order of appearance.

    A `#line` in a group the preprocessor skips is not obeyed (C's rule; seen on PoCL's and
    Intel's compilers: with an include inside `#ifndef CLOTH_GENERIC`, the generic build's
    errors after it were named 33 lines late), so after each `#else`, `#elif` and `#endif` of
    a group that holds an include the mark is given again; a file without includes in
    conditionals is left as it is.

    On the host, not by the compiler: GLSL has no #include, and the source handed to an
    OpenCL driver is then all of the program, so a program cache keyed on the source text
    (ours, PoCL's) sees an edit to an included file."""
    files: list[str] = []
    generated = {} if generated is None else generated

    def expand(name: str, text: str) -> str:
        number = len(files)
        files.append(name)
        out, last = [line_mark(1, number, name) + "\n"], 0
        holds_include: list[bool] = []  # per open conditional: does it hold an include yet
        directives = sorted([*_INCLUDE.finditer(text), *_CONDITIONAL.finditer(text)], key=lambda m: m.start())
        for match in directives:
            if match.re is _CONDITIONAL:
                kind = match.group(1)
                if kind in ("if", "ifdef", "ifndef"):
                    holds_include.append(False)
                    continue
                if not holds_include or not (holds_include.pop() if kind == "endif" else holds_include[-1]):
                    continue  # nothing of this group moved the lines
                out.append(text[last : match.end()])
            else:
                out.append(text[last : match.start()])
                holds_include = [True] * len(holds_include)
                included, special = match.groups()
                if included:
                    out.append(expand(included, read_kernel(included)))
                elif special in generated:
                    out.append(expand(f"<{special}>", generated[special]()))
                else:
                    raise ClothbenchError(f"{name}: unknown #include <{special}>")
            line = text.count("\n", 0, match.end()) + 2  # the line after the directive
            out.append("\n" + line_mark(line, number, name))
            last = match.end()
        out.append(text[last:])
        return "".join(out)

    return expand(filename, text), files


class _EveryGeneratedBlank(dict):
    """resolve_includes' `generated` that takes every `#include <name>` as empty text."""

    def __contains__(self, name) -> bool:
        return True

    def __missing__(self, name):
        return lambda: ""


def kernel_hash(*filenames: str) -> str:
    """12 hex digits of kernels/`filenames` and every file they include by name: what a kernel
    shape measured on them (backends/tuning.py) was measured on, so that an edit to any of them
    measures again. The generated `#include <...>` parts are left out: they follow the scene,
    which a tuning key names in its own fields."""
    digest = hashlib.sha256()
    for name in filenames:
        digest.update(resolve_includes(name, read_kernel(name), lambda *_: "", _EveryGeneratedBlank())[0].encode())
    return digest.hexdigest()[:12]


def c_float(x) -> str:
    """An exact C/OpenCL/CUDA float literal (hexadecimal), e.g. for -D build options."""
    return float.hex(float(np.float32(x))) + "f"


def glsl_float(x) -> str:
    """An exact GLSL float literal: the bit pattern, since GLSL has no hexadecimal floats."""
    bits = int(np.float32(x).view(np.uint32))
    return f"uintBitsToFloat(0x{bits:08x}u)"
