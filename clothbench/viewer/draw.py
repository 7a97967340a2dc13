"""Drawing into the viewer's window: the cloth and colliders as `clothbench render` draws
them (reports/render.py's Renderer, its meshes and shaders), into the window's framebuffer
with the trackball's camera and an optional wireframe, and the text overlay on top.

The overlay is text in a monospaced font, each glyph rasterised once by Pillow and lines
composed from the glyphs with NumPy into one RGBA image per panel, written into its rectangle
of a window-sized texture and blended over the frame there.
"""

from __future__ import annotations

import numpy as np

from clothbench.reports.render import Renderer

FONT_SIZE = 13
PANEL = (16, 20, 28, 178)  # RGBA behind the text
TEXT = (236, 238, 242, 255)
DIM = (170, 178, 190, 255)
WARN = (255, 196, 92, 255)
PAD, GAP = 8, 10

_OVERLAY_VERTEX = """#version 330 core
out vec2 uv;
void main() {
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);  // (0,0) (2,0) (0,2)
    uv = vec2(p.x, 1.0 - p.y);  // the image's row 0 is its top, uploaded as the texture's first row
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""
_OVERLAY_FRAGMENT = """#version 330 core
uniform sampler2D image;
in vec2 uv;
out vec4 colour;
void main() { colour = texture(image, uv); }
"""


class WindowRenderer(Renderer):
    """render.Renderer drawing into `target` (the window's framebuffer) instead of reading
    the image back: the multisampled frame is resolved straight into the window."""

    def __init__(self, device, scene, size, target):
        super().__init__(device, scene, size)
        self.target = target
        self.wireframe = False

    def _draw(self, cloth_vao):
        self._render(cloth_vao)
        ctx = self.gl.ctx
        ctx.copy_framebuffer(self.target, self.fbo)  # resolve the multisampling into the window
        return None


def _font(size: int):
    from PIL import ImageFont

    for name in ("DejaVuSansMono.ttf", "LiberationMono-Regular.ttf"):
        try:
            return ImageFont.truetype(name, size)
        except OSError:
            continue
    return ImageFont.load_default(size=size)


class Glyphs:
    """A monospaced font as one coverage tile per printable ASCII character, so that a line of
    text is composed by indexing (NumPy) instead of rasterised again every frame."""

    FIRST, LAST = 32, 126

    def __init__(self, size: int = FONT_SIZE):
        from PIL import Image, ImageDraw

        font = _font(size)
        chars = [chr(c) for c in range(self.FIRST, self.LAST + 1)]
        self.width = max(1, round(max(font.getlength(c) for c in chars)))
        self.height = size + 4
        tiles = np.zeros((len(chars) + 1, self.height, self.width), dtype=np.float32)  # last: unknown
        for i, c in enumerate(chars + ["?"]):
            tile = Image.new("L", (self.width, self.height), 0)
            ImageDraw.Draw(tile).text((0, 1), c, font=font, fill=255)
            tiles[i] = np.asarray(tile, dtype=np.float32) / 255
        self.tiles = tiles

    def line(self, text: str) -> np.ndarray:
        """Coverage (height, width * len(text)) of one line, 0..1."""
        codes = np.frombuffer(text.encode("ascii", "replace"), dtype=np.uint8).astype(np.int64) - self.FIRST
        codes[(codes < 0) | (codes > self.LAST - self.FIRST)] = len(self.tiles) - 1
        return np.concatenate(self.tiles[codes], axis=1) if len(codes) else np.zeros((self.height, 0), np.float32)


def wrap(text: str, width: int) -> list[str]:
    """`text` in lines of at most `width` characters, broken between words (inside a word
    only where it is longer than a line)."""
    width = max(1, width)
    lines, line = [], ""
    for word in text.split():
        while len(word) > width:
            if line:
                lines.append(line)
                line = ""
            lines.append(word[:width])
            word = word[width:]
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return lines + [line] if line else lines


def fit_lines(items: list[tuple[str, tuple]], width: int) -> list[tuple[str, tuple]]:
    """An overlay panel's (text, colour) lines, each at most `width` characters: a longer one (a
    backend's refusal names every backend that could run) wrapped in its colour."""
    return [(part, colour) for text, colour in items for part in (wrap(text, width) if len(text) > width else [text])]


def layout(panels: list[tuple[str, list]], size: tuple[int, int], g: Glyphs) -> list[tuple[str, int, int, np.ndarray]]:
    """Each panel as (corner, x, y from the top, RGBA uint8 image): `panels` are (corner, lines),
    corner one of 'top-left', 'top-right', 'bottom-left'; a line is text or (text, colour).
    The bottom panel's lines (the last event, the keys) wider than the window go on below
    (fit_lines); the top panels are tables, a column to a line, cut at the window's edge
    (wrapped, a narrow window's run panel would cover the cloth)."""
    w, h = size
    out = []
    for corner, lines in panels:
        if not lines:
            continue
        items = [(line, TEXT) if isinstance(line, str) else line for line in lines]
        if corner == "bottom-left":
            items = fit_lines(items, (w - 2 * GAP - 2 * PAD) // g.width)
        pw = min(w - 2 * GAP, max(len(text) for text, _ in items) * g.width + 2 * PAD)
        ph = min(h - 2 * GAP, len(items) * g.height + 2 * PAD)
        x = GAP if corner != "top-right" else max(0, w - GAP - pw)
        y = GAP if corner != "bottom-left" else max(0, h - GAP - ph)
        cover = np.zeros((ph, pw), dtype=np.float32)  # text coverage, 0..1
        ink = np.zeros((ph, 1, 4), dtype=np.float32)  # each row's text colour
        for i, (text, colour) in enumerate(items):
            top = PAD + i * g.height
            line = g.line(text)[: max(0, ph - top), : max(0, pw - PAD)]
            cover[top : top + line.shape[0], PAD : PAD + line.shape[1]] = line
            ink[top : top + g.height] = colour
        back = np.array(PANEL, dtype=np.float32)
        panel = back + cover[..., None] * (ink - back)
        out.append((corner, x, y, (panel + 0.5).astype(np.uint8)))
    return out


def clear_span(placed: list[tuple[str, int, int, np.ndarray]], width: int) -> tuple[int, int]:
    """The pixel columns [left, right) between the top panels (the run panel at the left, the
    profiler at the right, where they are): the cloth is framed there, where no text covers it
    (camera.Trackball.keep_clear_of)."""
    left = max((x + image.shape[1] + GAP for corner, x, _, image in placed if corner == "top-left"), default=0)
    right = min((x - GAP for corner, x, _, image in placed if corner == "top-right"), default=width)
    return left, right


class Overlay:
    """Panels of text over the frame: each a list of lines, placed at a corner."""

    def __init__(self, device, size: tuple[int, int]):
        self.gl, self.size = device, size
        self.glyphs = Glyphs()
        with device:
            ctx = device.ctx
            self.program = ctx.program(vertex_shader=_OVERLAY_VERTEX, fragment_shader=_OVERLAY_FRAGMENT)
            self.texture = ctx.texture(size, 4)
            self.vao = ctx.vertex_array(self.program, [])

    def place(self, panels) -> list[tuple[str, int, int, np.ndarray]]:
        """`panels` laid out in this window (layout): before the frame is drawn, so that the
        camera can keep the cloth clear of them."""
        return layout(panels, self.size, self.glyphs)

    def draw(self, target, placed) -> None:
        """Blend the `placed` panels over what `target` (the window's framebuffer) holds. Only
        the panels' rectangles are written and drawn (a software rasteriser pays for every pixel)."""
        h = self.size[1]
        with self.gl:
            ctx = self.gl.ctx
            for _, x, y, image in placed:  # texture row r is screen row r from the top (the shader)
                self.texture.write(image.tobytes(), viewport=(x, y, image.shape[1], image.shape[0]))
            self.texture.use(location=0)
            self.program["image"].value = 0
            target.use()
            ctx.disable(ctx.DEPTH_TEST | ctx.CULL_FACE)
            ctx.enable(ctx.BLEND)
            ctx.blend_func = ctx.SRC_ALPHA, ctx.ONE_MINUS_SRC_ALPHA
            for _, x, y, image in placed:
                ph, pw = image.shape[:2]
                ctx.scissor = (x, h - y - ph, pw, ph)
                self.vao.render(mode=ctx.TRIANGLES, vertices=3)
            ctx.scissor = None
            ctx.disable(ctx.BLEND)

    def release(self) -> None:
        with self.gl:
            for obj in (self.vao, self.texture, self.program):
                obj.release()
