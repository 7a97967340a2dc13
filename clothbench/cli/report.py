"""`clothbench report`: one self-contained HTML page (figures inline as SVG, nothing fetched)
for a whole study, from the CSVs of sweep, accuracy, stability, energy and pbd-study
(reports/html.py)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from clothbench.errors import ClothbenchError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help="one self-contained HTML page from sweep, accuracy, stability, energy and pbd-study CSVs",
        description="Write one HTML page holding a whole study: for every CSV given (a sweep, an accuracy run "
        "and its -artefacts CSV, a stability run, an energy study, a PBD study; each recognised by its columns) its figures, "
        "inline as SVG, and its tables, with the machine and drivers the rows were measured on. Nothing in the page is "
        "fetched from elsewhere: it opens offline and can be mailed or published as it is.",
    )
    p.add_argument(
        "results",
        nargs="+",
        metavar="RESULTS",
        help="CSV files written by clothbench sweep, accuracy, stability, energy or pbd-study",
    )
    p.add_argument("--out", default="report.html", help="the HTML file to write (default report.html)")
    p.add_argument("--title", default="clothbench report", help="the page's title")
    p.set_defaults(func=cmd_report)


def cmd_report(args) -> int:
    from clothbench.progress import waiting
    from clothbench.reports.results_files import read_results

    out = Path(args.out)
    paths = list(dict.fromkeys(Path(p) for p in args.results))  # each file once, in the order given
    for p in paths:
        if p.exists() and out.exists() and out.samefile(p):
            raise ClothbenchError(f"--out {out} is one of the RESULTS files: choose another --out")
    with _Writable(out) as target, waiting("building the report: reading the results files") as say:
        files = [read_results(p) for p in paths]  # every file checked before anything is drawn
        say("building the report: drawing its figures")
        from clothbench.reports.html import build_report  # matplotlib: most of a second to import

        page, count = build_report(files, args.title)
        target.write(page)
    kinds = ", ".join(dict.fromkeys(f.kind for f in files))
    print(f"wrote {out} ({count} figures from {len(files)} files: {kinds})")
    return 0


class _Writable:
    """--out, proven writable before any work: a temporary file beside it is opened at once and
    renamed onto it when the page is complete, so a failed run leaves no half-written page."""

    def __init__(self, out: Path):
        self.out = out
        if out.is_dir():
            raise ClothbenchError(f"--out {out} is a directory: name the HTML file to write")
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
        except OSError as e:
            raise ClothbenchError(f"cannot write {out}: {e.strerror}") from None
        self.tmp = Path(name)
        self.file = os.fdopen(fd, "w", encoding="utf-8")

    def __enter__(self):
        return self.file

    def __exit__(self, exc_type, *_):
        self.file.close()
        if exc_type is None:
            try:
                os.chmod(self.tmp, 0o644)  # mkstemp's 0600 is for secrets; a report is for reading
                os.replace(self.tmp, self.out)
                return
            except OSError as e:
                self.tmp.unlink(missing_ok=True)
                raise ClothbenchError(f"cannot write {self.out}: {e.strerror}") from None
        self.tmp.unlink(missing_ok=True)
