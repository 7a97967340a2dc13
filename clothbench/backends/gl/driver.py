"""The `driver` of every GL backend: the GL renderer and version strings of its context."""

from __future__ import annotations


class GLDriverInfo:
    """Backend.driver for a backend whose GL context is `self.gl` (a gl.context.GLDevice)."""

    @property
    def driver(self) -> str:
        """GL_RENDERER and GL_VERSION as the driver spells them, e.g. "llvmpipe (LLVM 15.0.6,
        256 bits), OpenGL 4.5 (Core Profile) Mesa 22.3.6", and the provider where it is not
        EGL: the same renderer behind OSMesa is another library build."""
        return gl_driver(self.gl)


def gl_driver(device) -> str:
    """The driver of a GL context (a gl.context.GLDevice): what GLDriverInfo.driver and the
    GL probe's Availability.driver say."""
    info = device.ctx.info
    provider = "" if device.provider == "egl" else f", via {device.provider}"
    return f"{info['GL_RENDERER']}, OpenGL {info['GL_VERSION']}{provider}"
