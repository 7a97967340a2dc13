"""clothbench: one cloth simulation through interchangeable GPGPU backends, timed and checked."""

__version__ = "0.1.0"
