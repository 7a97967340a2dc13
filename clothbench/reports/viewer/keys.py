"""The viewer's keys: their names, what each does, and `--keys "40:F3,80:F2"` scripts.

A key is named as on the keyboard: F1 ... F12, the digits, the letters (upper case), `space`,
the arrows `left right up down`, and `escape`. The same names come from a real keyboard
(`name_of`, from the window library's key codes) and from a `--keys` script, so a scripted
run presses exactly what a person would.
"""

from __future__ import annotations

import string

from clothbench.backends import BACKENDS
from clothbench.errors import ClothbenchError

# The F-keys in the chapter's order (F1 the CPU, F2 GLSL, F3 OpenCL, F4 CUDA), F5 GLSL compute
# (its key before the registry grew), then the rest of the registry in its order.
CHAPTER_ORDER = ("numpy", "glsl", "opencl", "cuda", "glsl-compute")
BACKEND_ORDER = tuple(CHAPTER_ORDER) + tuple(n for n in BACKENDS if n not in CHAPTER_ORDER)
BACKEND_KEYS = {f"F{i}": name for i, name in enumerate(BACKEND_ORDER, start=1)}
GRID_KEYS = {"1": 32, "2": 64, "3": 128, "4": 256, "5": 512}
COLLIDER_KEYS = {"S": "sphere", "C": "cylinder", "G": "plane"}  # G: the ground plane
ROTATE_KEYS = {"left": (0, -1), "right": (0, 1), "up": (-1, 0), "down": (1, 0)}  # (pitch, yaw) steps
ZOOM_KEYS = {"Z": 1, "X": -1}  # zoom in, out

KEY_NAMES = (
    tuple(f"F{i}" for i in range(1, 13))
    + tuple(string.digits)
    + tuple(string.ascii_uppercase)
    + ("space", "left", "right", "up", "down", "escape")
)

# What each key does, in the order the help lists them (also the --help epilog).
HELP = (
    ("F1-F{}".format(len(BACKEND_ORDER)), "backend: " + ", ".join(f"F{i} {n}" for i, n in enumerate(BACKEND_ORDER, 1))),
    ("1-5", "grid " + ", ".join(f"{k} {n}x{n}" for k, n in GRID_KEYS.items()) + " (restarts the cloth)"),
    ("S C G", "toggle the spheres, the cylinders, the ground plane"),
    ("R", "reset the cloth to its start"),
    ("space", "pause / run"),
    ("N", "one frame's steps while paused"),
    ("W", "wireframe"),
    ("P", "the profiler"),
    ("E", "float64 NumPy shadow run and the error against it"),
    ("H", "this help"),
    ("mouse", "drag: trackball; wheel: zoom (keys: arrows rotate, Z X zoom, O home view)"),
    ("Q escape", "quit"),
)


def normalise(name: str) -> str:
    """A key name as the viewer spells it ('f3' -> 'F3', 'Space' -> 'space'), or
    ClothbenchError naming the keys there are."""
    text = name.strip()
    for candidate in (text.upper(), text.lower()):
        if candidate in KEY_NAMES:
            return candidate
    raise ClothbenchError(
        f"unknown key {name!r} (keys: F1..F12, 0-9, A-Z, space, left, right, up, down, escape)"
    )


def parse_script(text: str) -> dict[int, list[str]]:
    """'40:F3,80:F2,120:P' -> {40: ['F3'], 80: ['F2'], 120: ['P']}: the keys pressed before
    frame FRAME is stepped (frames count from 1), in the order given."""
    script: dict[int, list[str]] = {}
    for part in text.split(","):
        if not part.strip():
            continue
        frame, sep, key = part.partition(":")
        try:
            number = int(frame)
        except ValueError:
            number = 0
        if not sep or number < 1:
            raise ClothbenchError(
                f"--keys takes FRAME:KEY pairs with FRAME >= 1, like 40:F3,80:F2,120:P; got {part.strip()!r}"
            )
        script.setdefault(number, []).append(normalise(key))
    return script


def window_key_names(keys) -> dict:
    """The window library's key codes (a moderngl-window Keys class) -> the viewer's names."""
    names = {f"F{i}": f"F{i}" for i in range(1, 13)}
    names.update({f"NUMBER_{d}": d for d in string.digits})
    names.update({f"NUMPAD_{d}": d for d in string.digits})
    names.update({c: c for c in string.ascii_uppercase})
    names.update(SPACE="space", LEFT="left", RIGHT="right", UP="up", DOWN="down", ESCAPE="escape")
    codes = {}
    for attr, name in names.items():
        code = getattr(keys, attr, "undefined")
        if code != "undefined":
            codes.setdefault(code, name)
    return codes
