"""When a timed row's figure means little: the machine was `busy` while it ran, or its chunks
were `unstable` (spread too wide for its median to stand for the step). `compare` calls a change
between two such rows inconclusive rather than a regression or a gain.

`unstable` is pyperf's rule of thumb (a standard deviation over 10 % of the mean) made robust:
the standard deviation is estimated from the chunks' interquartile range (IQR / 1.349, exact for
normal noise) and set against their median, the figure a row reports. One chunk the machine
stalled (a page fault, a timer tick on a busy core) moves neither the median nor the IQR, so it
does not make a row unstable; a spread through the middle half of the chunks does.
"""

from __future__ import annotations

import math

import numpy as np

from clothbench.harness.sweep_csv import parse_chunks

UNSTABLE_SPREAD = 0.10  # a robust standard deviation over this share of the median: unstable
IQR_PER_SIGMA = 1.349  # the interquartile range of a normal distribution, in standard deviations
MIN_CHUNKS_FOR_SPREAD = 4  # fewer chunks have no quartiles worth the name: spread unknown


def robust_spread(chunks: list[float]) -> float | None:
    """(IQR / 1.349) / median of `chunks`: a relative standard deviation that one outlier cannot
    move. None with fewer than MIN_CHUNKS_FOR_SPREAD chunks or a median that is not positive."""
    if len(chunks) < MIN_CHUNKS_FOR_SPREAD:
        return None
    q1, median, q3 = (float(q) for q in np.percentile(chunks, [25, 50, 75]))  # as RunResult.spread's IQR
    if not median > 0 or not math.isfinite(median):
        return None
    return (q3 - q1) / IQR_PER_SIGMA / median


def doubts(busy: bool | None, load: str, chunks: list[float]) -> list[str]:
    """Why a timing's median is not to be trusted as a measure of the step, one phrase each:
    'busy (...)' where the machine was (machine_load's verdict over the run, with its why),
    'unstable (spread N % of the median)' where its chunks say so; [] for neither."""
    out = []
    if busy:
        out.append(f"busy ({load})" if load else "busy")
    spread = robust_spread(chunks)
    if spread is not None and spread > UNSTABLE_SPREAD:
        out.append(f"unstable (spread {spread:.0%} of the median)")
    return out


def row_doubts(row: dict, chunks: list[float] | None = None) -> list[str]:
    """doubts() of a sweep row: its `busy` and `load` columns (empty in files older than them)
    and its chunks, `chunks` where the caller has them, else read from its chunk_ms (none where
    that is missing or unreadable)."""
    if chunks is None:
        try:
            chunks = parse_chunks(row.get("chunk_ms", ""))
        except ValueError:
            chunks = []
    return doubts(row.get("busy", "").lower() == "true", row.get("load", ""), chunks)


__all__ = ["UNSTABLE_SPREAD", "doubts", "robust_spread", "row_doubts"]
