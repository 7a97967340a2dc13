"""The viewer's keys: their names, what each does, and `--keys "40:F3,80:F2"` scripts.

A key is named as on the keyboard: F1 ... F12, shift+F1 ... shift+F12, the digits, the
letters (upper case), `space`, the arrows `left right up down`, and `escape`. The same names
come from a real keyboard (`name_of`, from the window library's key codes and modifiers) and
from a `--keys` script, so a scripted run presses exactly what a person would. Each backend's
key is its registry entry's (BackendEntry.view_key), read when asked, so a backend added to
the registry has its key here, in the help and in the overlay.
"""

from __future__ import annotations

import string

from clothbench.backends import BACKENDS
from clothbench.errors import ClothbenchError

# moderngl-window names F1..F12 and no further (it has no F13, and few keyboards do), so past
# F12 a backend's key is shift and an F-key, which every keyboard has
F_KEYS = tuple(f"F{i}" for i in range(1, 13))
SHIFT = "shift+"
BACKEND_KEY_NAMES = F_KEYS + tuple(SHIFT + k for k in F_KEYS)
GRID_KEYS = {"1": 32, "2": 64, "3": 128, "4": 256, "5": 512}
COLLIDER_KEYS = {"S": "sphere", "C": "cylinder", "G": "plane"}  # G: the ground plane
ROTATE_KEYS = {"left": (0, -1), "right": (0, 1), "up": (-1, 0), "down": (1, 0)}  # (pitch, yaw) steps
ZOOM_KEYS = {"Z": 1, "X": -1}  # zoom in, out

KEY_NAMES = (
    BACKEND_KEY_NAMES
    + tuple(string.digits)
    + tuple(string.ascii_uppercase)
    + ("space", "left", "right", "up", "down", "escape")
)


def backend_keys() -> dict[str, str]:
    """key -> backend, from the registry's view keys, in key order; ClothbenchError where an
    entry's key is none the viewer has or is another backend's too."""
    keys: dict[str, str] = {}
    for name, entry in BACKENDS.items():
        if entry.view_key not in BACKEND_KEY_NAMES:
            has = _span(BACKEND_KEY_NAMES)
            raise ClothbenchError(f"{name}'s view key {entry.view_key!r} is none the viewer has ({has})")
        if entry.view_key in keys:
            raise ClothbenchError(f"{name} and {keys[entry.view_key]} both have view key {entry.view_key}")
        keys[entry.view_key] = name
    return {k: keys[k] for k in BACKEND_KEY_NAMES if k in keys}


def key_of(backend: str) -> str:
    """The viewer's key for `backend` (a registry name); none for a playback (view --from)."""
    return {name: k for k, name in backend_keys().items()}.get(backend, "")


def _span(keys) -> str:
    """Keys as runs: 'F1-F12, shift+F1-F2'."""
    runs: list[list[str]] = []
    for key in keys:
        prefix, number = (SHIFT, key[len(SHIFT) :]) if key.startswith(SHIFT) else ("", key)
        last = runs[-1] if runs else None
        if last and last[0] == prefix and int(last[2][1:]) + 1 == int(number[1:]):
            last[2] = number
        else:
            runs.append([prefix, number, number])
    return ", ".join(f"{p}{a}" if a == b else f"{p}{a}-{b}" for p, a, b in runs)


# the key names, said in a line (an unknown key's error, `view --help`)
KEYS_TEXT = f"{_span(BACKEND_KEY_NAMES)}, digits, letters, space, left, right, up, down, escape"


def backend_key_span() -> str:
    """The backend keys as runs, for the overlay's hint: 'F1-F12, shift+F1-F2'."""
    return _span(backend_keys())


def _backend_help() -> list[tuple[str, str]]:
    """A help line per kind of backend key (F-keys, then shift+F-keys)."""
    keys = backend_keys()
    kinds = [[k for k in keys if k.startswith(SHIFT) == shifted] for shifted in (False, True)]
    return [(_span(ks), "backend: " + ", ".join(f"{k} {keys[k]}" for k in ks)) for ks in kinds if ks]


def help_lines() -> tuple[tuple[str, str], ...]:
    """What each key does, in the order the help lists them (the overlay's H and `view --help`)."""
    return (
        *_backend_help(),
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
    by_lower = {k.lower(): k for k in KEY_NAMES}
    text = name.strip().lower()
    if text in by_lower:
        return by_lower[text]
    raise ClothbenchError(f"unknown key {name!r} (keys: {KEYS_TEXT})")


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
    """The window library's key codes (a moderngl-window Keys class) -> the viewer's names
    (without a modifier: name_of adds shift)."""
    names = {k: k for k in F_KEYS}
    names.update({f"NUMBER_{d}": d for d in string.digits})
    names.update({f"NUMPAD_{d}": d for d in string.digits})
    names.update({c: c for c in string.ascii_uppercase})
    names.update(SPACE="space", LEFT="left", RIGHT="right", UP="up", DOWN="down", ESCAPE="escape")
    codes = {}
    for attr, name in names.items():
        code = getattr(keys, attr, "undefined")  # a key this window library does not name is not pressed
        if code != "undefined":
            codes.setdefault(code, name)
    return codes


def name_of(codes: dict, key, shift: bool) -> str | None:
    """The viewer's name of a key pressed (codes: window_key_names), shift+ before an F-key
    pressed with shift; None for a key the viewer has no name for."""
    name = codes.get(key)
    return SHIFT + name if shift and name in F_KEYS else name
