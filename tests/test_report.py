"""`clothbench report`: one self-contained HTML page from the results CSVs, checked as text
and rendered in headless Chromium (Debian's chromium and chromedriver, driven by selenium):
the page renders, every figure has a size, the console is clean, a screenshot is taken."""

from __future__ import annotations

import csv
import re
import shutil
from pathlib import Path

import pytest

from clothbench.cli import main
from clothbench.reports.accuracy_plots import energy_chart
from clothbench.reports.html import SECTIONS, machine_section
from clothbench.reports.page import Exact, esc, num
from clothbench.analysis.convergence import FITTED
from clothbench.reports.results_files import (
    KINDS,
    REQUIRED,
    ResultsFile,
    analysis_rows,
    read_results,
    recognise,
    unfinished,
)

RESULTS = Path(__file__).resolve().parent.parent / "results"
COMMITTED = sorted(RESULTS.glob("*.csv"))
SWEEP = RESULTS / "cpu-llvmpipe-pocl.csv"
PBD_SWEEP = RESULTS / "pbd-curtain.csv"
ACCURACY = RESULTS / "accuracy-drape.csv"
STABILITY = RESULTS / "stability.csv"
ENERGY = RESULTS / "energy" / "energy-drape-8.csv"  # clothbench energy's committed study
PBD_STUDY = RESULTS / "pbd-study" / "pbd-study.csv"  # clothbench pbd-study's
WINDOW = (1280, 900)
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    f"--window-size={WINDOW[0]},{WINDOW[1]}",
    "--force-device-scale-factor=1",
)


def every_csv(test):
    """A test of `study`, the report of every committed CSV (a minute or more to make): full
    tier, and one xdist worker for them all (an xdist_group), so that the fixture is made once,
    not in each worker; session-scoped, as a module fixture is made again each time that worker
    comes back to this module from another."""
    return pytest.mark.full(pytest.mark.xdist_group("report-of-every-committed-csv")(test))


@pytest.fixture(scope="session")
def study(tmp_path_factory) -> tuple[Path, str]:
    """The report of every committed results CSV (`clothbench report results/*.csv`)."""
    out = tmp_path_factory.mktemp("report") / "r.html"
    assert main(["report", *map(str, COMMITTED), "--out", str(out)]) == 0
    return out, out.read_text(encoding="utf-8")


def top_section(page: str, section_id: str) -> str:
    """The HTML of one top-level section: from its opening tag to the next <h2>."""
    start = page.index(f'<section id="{section_id}">')
    end = page.find("<h2>", start + len(section_id) + 30)
    return page[start : end if end > 0 else len(page)]


def section_id(kind: str, path: Path) -> str:
    return re.sub(r"[^a-z0-9]+", "-", f"{kind} {path}".lower()).strip("-")


@every_csv
def test_committed_results_are_each_recognised(study):
    _, page = study
    for path, what in (
        (SWEEP, "a sweep"),
        (PBD_SWEEP, "a sweep"),
        (ACCURACY, "an accuracy run"),
        (RESULTS / "accuracy-drape-artefacts.csv", "PBD artefacts"),
        (STABILITY, "a stability run"),
    ):
        assert re.search(rf"{re.escape(str(path))}</a></td><td>{what}", page), path
    assert "This study did not finish" not in page  # every committed accuracy study is a finished one


@every_csv
def test_page_holds_a_figure_for_each_input_kind(study):
    _, page = study
    for kind, path, at_least in (
        ("sweep", SWEEP, 4),
        ("sweep", PBD_SWEEP, 3),
        ("accuracy", ACCURACY, 2),
        ("stability", STABILITY, 1),
    ):
        part = top_section(page, section_id(kind, path))
        assert part.count("<svg") >= at_least, f"{path.name}: {part.count('<svg')} figures"
    assert 'aria-label="Stability against the bound"' in top_section(page, section_id("stability", STABILITY))


@every_csv
def test_sweep_has_speed_against_error_with_its_pareto_front(study):
    _, page = study
    part = top_section(page, section_id("sweep", SWEEP))
    figure = re.search(r'<svg[^>]*aria-label="Speed against error".*?</svg>', part, re.S)
    assert figure, "no speed-against-error figure in the sweep's section"
    assert "Pareto front" in figure[0]  # matplotlib keeps each text as a comment beside its glyphs
    front = part[part.index("Pareto front: speed against error") :]
    assert "opencl fast/resident/ls=auto" in front.split("</table>")[0]  # the README's fastest at 256x256


@every_csv
def test_the_readme_tables_are_on_the_page(study):
    _, page = study
    part = top_section(page, section_id("sweep", SWEEP))
    ms = part[part.index(">ms per step<") :].split("</table>")[0]
    assert [f"{n}×{n}" for n in (32, 64, 128, 256, 512)] == re.findall(r"<th>(\d+×\d+)</th>", ms)
    row = re.search(r"<tr><td>opencl fast/resident/ls=auto</td>.*?</tr>", ms)[0]
    assert re.findall(r'class="num[^"]*">([\d.,]+)</td>', row)[3] == "0.241"  # README: 256x256
    assert ms.count('<tr class="peer">') == 5  # taichi x2, warp, numba x2
    peers = part[part.index(">Peers against clothbench<") :].split("</table>")[0]
    assert "7.1×" in peers and "taichi strict" in peers  # README's 256x256 row
    assert ">Verlet against PBD<" in top_section(page, section_id("sweep", PBD_SWEEP))
    assert ">Verlet against PBD<" not in part  # one solver only


@every_csv
def test_page_is_self_contained_with_ids_of_its_own(study):
    _, page = study
    links = re.findall(r'(?:href|src)="([^"]*)"', page)
    assert links and all(link.startswith("#") for link in links), [x for x in links if not x.startswith("#")][:3]
    assert "url(http" not in page and "@import" not in page
    ids = re.findall(r'\bid="([^"]+)"', page)
    assert len(ids) == len(set(ids)), "two elements share an id (inlined SVGs must rename theirs)"
    assert all(f"url(#{i})" not in page or i in ids for i in re.findall(r"url\(#([^)]+)\)", page))


def _write_rows(path: Path, rows: list[dict]) -> Path:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def test_every_kind_of_results_csv_is_recognised_by_its_own_columns_and_has_a_section():
    # the registry (results_files.KINDS) against the page (html.SECTIONS): a kind added to one
    # and not the other is a file the report would recognise and not show, or the reverse
    assert list(SECTIONS) == [k.name for k in KINDS]
    for kind in KINDS:
        assert recognise("f.csv", REQUIRED[kind.name]) == kind.name


def test_machine_section_says_when_rows_come_from_different_machines(tmp_path):
    rows = list(csv.DictReader(SWEEP.open()))[:42]
    for r in rows[21:]:
        r["cpu"], r["env"] = "Intel Xeon", "OMP_NUM_THREADS=4"
    # with chunk_ms, a newer sweep's column: read, not needed
    mixed = _write_rows(tmp_path / "mixed.csv", [{**r, "chunk_ms": "0.1 0.2"} for r in rows])
    machine = machine_section([read_results(mixed)]).render()  # the report's section, without its figures
    assert "come from at least 2 different machines" in machine and "differ in cpu, env" in machine
    assert "OMP_NUM_THREADS=4" in machine


def test_the_dirty_note_is_there_only_when_a_row_is_dirty():
    rows = list(csv.DictReader(SWEEP.open()))[:21]
    assert not any("+dirty" in r["git_commit"] for r in rows)
    note = "'+dirty': the commit had changes not yet committed."
    assert note not in machine_section([ResultsFile(SWEEP, "sweep", rows)]).render()
    rows[3] = {**rows[3], "git_commit": f"{rows[3]['git_commit']}+dirty (version 0.1.0)"}  # an installed copy's
    assert note in machine_section([ResultsFile(SWEEP, "sweep", rows)]).render()


def _device_rows(machine: str) -> list[tuple[str, ...]]:
    """(backend, device, driver, in) of each row of the machine section's device table."""
    body = re.search(
        r"<th>device, as its driver names it</th><th>driver</th><th>in</th></tr></thead><tbody>(.*?)"
        r"</tbody>",
        machine,
        re.S,
    )
    assert body, "the device table has a driver column"
    return [tuple(re.findall(r"<td[^>]*>(.*?)</td>", tr)) for tr in re.findall(r"<tr[^>]*>(.*?)</tr>", body.group(1))]


def test_the_device_table_names_each_rows_driver_and_says_when_a_file_has_none(tmp_path):
    # one CPU is "Intel(R) Xeon(R) Processor" under Intel's OpenCL runtime and the CPU
    # backends alike: the driver column says which runtime ran a row; a file older than the
    # column still reports, its driver "not recorded"
    rows = [r for r in csv.DictReader(SWEEP.open()) if r["grid"] == "32" and r["backend"] in ("numpy", "opencl")]
    assert "driver" not in rows[0]
    device = {r["backend"]: r["device"] for r in rows}
    drivers = {"opencl": "Intel(R) OpenCL: OpenCL 3.1 LINUX; driver 2026.22", "numpy": ""}
    recorded = _write_rows(tmp_path / "recorded.csv", [{**r, "driver": drivers.get(r["backend"], "x 1")} for r in rows])
    older = _write_rows(tmp_path / "older.csv", rows)
    table = _device_rows(machine_section([read_results(recorded), read_results(older)]).render())
    named = {(b, d, v): n for b, d, v, n in table}
    for backend in ("opencl", "numpy"):
        key = (backend, esc(device[backend]))
        assert named[(*key, esc(drivers[backend]))] == str(recorded), table
        assert named[(*key, "not recorded")] == str(older), table
    assert len(named) == 4, table


@pytest.mark.full  # a report of a whole sweep, twice
@pytest.mark.parametrize("cpu, differs", [("AMD EPYC", False), ("Apple M2", True)])
def test_an_accuracy_run_that_names_its_cpu_is_compared_with_the_sweeps(cpu, differs, tmp_path):
    sweep = _write_rows(tmp_path / "sweep.csv", list(csv.DictReader(SWEEP.open()))[:21])
    accuracy = _write_rows(
        tmp_path / "acc.csv", [{**r, "cpu": cpu} for r in list(csv.DictReader(ACCURACY.open()))[:15]]
    )
    out = tmp_path / "r.html"
    assert main(["report", str(sweep), str(accuracy), "--out", str(out)]) == 0
    machine = top_section(out.read_text(encoding="utf-8"), "machine")
    assert f"acc.csv records only cpu: {cpu}" in machine
    assert ("different machines" in machine) == differs
    assert ("was measured on this one" in machine) != differs


def test_an_unfinished_accuracy_study_is_reported_with_the_orders_its_end_would_fit(tmp_path):
    # a study writes each row as it is measured, its fitted columns (order, order_points, in_fit)
    # empty until it completes (cli/study_files.py): the report of an interrupted one fits them
    # over the rows it has, as the study's end does, and says that the study did not finish
    finished = list(csv.DictReader(ACCURACY.open()))
    blank = _write_rows(tmp_path / "unfinished.csv", [{**r, **dict.fromkeys(FITTED, "")} for r in finished])
    done, partial = read_results(ACCURACY), read_results(blank)  # refused before: "order_points is ''"
    assert not unfinished(done) and unfinished(partial)
    fitted, refitted = analysis_rows(done), analysis_rows(partial)
    assert max(r.order_points for r in fitted) >= 3  # orders were fitted in the study: something to compare
    for d, p in zip(fitted, refitted, strict=True):
        assert (p.order_points, p.in_fit) == (d.order_points, d.in_fit), d.label
        # the same least-squares fit of the same numbers; its last bits are the LAPACK build's
        # (the file was fitted on another machine: 2e-15 apart here), so to 1e-12
        assert p.order == pytest.approx(d.order, rel=1e-12, nan_ok=True), d.label
    out = tmp_path / "r.html"  # the page says so where unfinished() holds (a finished one's: the study test above)
    few = _write_rows(tmp_path / "few.csv", [{**r, **dict.fromkeys(FITTED, "")} for r in finished[:15]])
    assert main(["report", str(few), "--out", str(out)]) == 0
    assert "This study did not finish" in out.read_text(encoding="utf-8")


def test_an_energy_study_is_reported_with_both_bounds_for_every_mode(tmp_path):
    # `clothbench energy`'s CSV, which the report refused before ("not a clothbench results
    # CSV"): a section with the figure of both bounds and a table row per mode; a damped run whose
    # energy only fell between readings says so in both, where a share of rounding means nothing
    rows = list(csv.DictReader(ENERGY.open()))
    fell = {r["label"] for r in rows if r["case"] == "damped" and float(r["max_rise_j"]) <= 0}
    rose = {r["label"] for r in rows if r["case"] == "damped"} - fell
    assert fell and rose  # the committed study has both kinds of run: both are checked
    out = tmp_path / "r.html"
    assert main(["report", str(ENERGY), "--out", str(out)]) == 0
    section = top_section(out.read_text(encoding="utf-8"), section_id("energy", ENERGY))
    assert section.count("<svg") == 1
    for r in rows:
        cells = re.search(rf"<tr[^>]*><td>{re.escape(esc(r['label']))}</td>(.*?)</tr>", section)
        assert cells, r["label"]
        if r["case"] == "undamped":
            assert f">{num(float(r['worst_drift_j']) / float(r['band_j']))}<" in cells[1], r["label"]
        else:
            assert ("never rose" in cells[1]) == (r["label"] in fell), r["label"]
    chart = energy_chart(analysis_rows(read_results(ENERGY)))
    assert len(chart.panels["undamped"]) == len(chart.panels["damped"]) == len({r["label"] for r in rows})
    damped_axes = chart.figure.axes[1]
    assert sum(t.get_text() == "never rose" for t in damped_axes.texts) == len(fell)
    assert len(damped_axes.patches) == len(rose)  # a bar for each run whose energy rose


def test_a_pbd_study_is_reported_with_its_figure_and_the_best_pair_at_each_cost(tmp_path):
    # `clothbench pbd-study`'s CSV, refused before as "not a clothbench results CSV"
    rows = [r for r in csv.DictReader(PBD_STUDY.open()) if r["status"] == "ok"]
    out = tmp_path / "r.html"
    assert main(["report", str(PBD_STUDY), "--out", str(out)]) == 0
    section = top_section(out.read_text(encoding="utf-8"), section_id("pbd-study", PBD_STUDY))
    assert section.count("<svg") == 1 and "frames of 1/60 s" in section
    assert "ms per frame: how busy not recorded" in section  # a study older than its busy column
    groups = {(r["scene"], r["method"], r["cost"]) for r in rows}
    assert len(groups) > 10  # both scenes, every method and cost
    for scene, method, cost in groups:
        best = min(
            (r for r in rows if (r["scene"], r["method"], r["cost"]) == (scene, method, cost)),
            key=lambda r: float(r["rms"]),
        )
        cells = f'<td>{scene}</td><td>{method}</td><td class="num">{cost}</td><td>{best["substeps"]} × {best["iterations"]}</td>'
        assert f'{cells}<td class="num">{num(float(best["rms"]))}</td>' in section, (scene, method, cost)


def test_numbers_are_formatted_for_people():
    assert num(21.863) == "21.9" and num(0.0608) == "0.0608" and num(1089.2) == "1,089"
    assert num(4.81e-4) == "4.81&#8239;×&#8239;10<sup>−4</sup>"
    assert num(Exact(5e-4)) == "0.0005" and num(Exact(100000.0)) == "100,000" and num(float("nan")) == "–"


def _bad_input_cases(tmp: Path) -> dict[str, tuple[list[str], str]]:
    (tmp / "binary.csv").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    (tmp / "other.csv").write_text("name,value\nx,1\n")
    (tmp / "empty.csv").write_text("")
    header = SWEEP.read_text().splitlines()[0]
    (tmp / "header-only.csv").write_text(header + "\n")
    (tmp / "torn.csv").write_text(header.replace(",ms_median", "") + "\n")
    (tmp / "a-file").write_text("x")
    good = str(STABILITY)
    return {
        "missing file": ([str(tmp / "nope.csv")], "no such file"),
        "a directory": ([str(tmp)], "is a directory"),
        "binary": ([str(tmp / "binary.csv")], "not UTF-8 text"),
        "not ours": ([str(tmp / "other.csv")], "not a clothbench results CSV"),
        "empty": ([str(tmp / "empty.csv")], "is empty"),
        "no rows": ([str(tmp / "header-only.csv")], "no rows"),
        "a sweep lacking a column": ([str(tmp / "torn.csv")], "lacks column(s) ms_median"),
        "one bad among good": ([good, str(tmp / "other.csv")], "other.csv is not"),
        "--out a directory": ([good, "--out", str(tmp)], "is a directory"),
        "--out under a file": ([good, "--out", str(tmp / "a-file" / "r.html")], "cannot write"),
        "--out an input": ([good, "--out", good], "is one of the RESULTS files"),
    }


BAD_CASES = (
    "missing file",
    "a directory",
    "binary",
    "not ours",
    "empty",
    "no rows",
    "a sweep lacking a column",
    "one bad among good",
    "--out a directory",
    "--out under a file",
    "--out an input",
)


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_input_is_one_line_and_exit_2_before_any_work(case, tmp_path, capsys, monkeypatch):
    import clothbench.reports.html as html

    def never(*_a, **_k):
        raise AssertionError("the report was built despite bad input")

    monkeypatch.setattr(html, "build_report", never)
    args, says = _bad_input_cases(tmp_path)[case]
    if "--out" not in args:
        args = args + ["--out", str(tmp_path / "out" / "r.html")]
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main(["report", *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("clothbench: error: ") and says in err, err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.rglob("*") if p.name != "out") == [b for b in before if b != "out"]
    assert not list(tmp_path.rglob("*.html")) and not list(tmp_path.rglob("*.tmp"))


def chromium(tmp_path: Path):
    """A headless Chromium under selenium with a fresh profile and no network use, or a skip
    saying what is missing."""
    binary, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if not binary or not driver:
        pytest.skip("Chromium or chromedriver not installed (Debian: apt-get install chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium not installed (pip install '.[test]')")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path / 'chromium-profile'}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(driver), options=options)


FIGURE_SIZES = """
return Array.from(document.querySelectorAll('svg, img')).map(e => {
  const box = e.getBoundingClientRect();
  const drawn = e.tagName.toLowerCase() === 'svg' ? e.querySelector('g').getBBox() : null;
  return {id: e.id, width: box.width, height: box.height,
          drawn: drawn ? drawn.width * drawn.height : (e.complete ? e.naturalWidth : 0)};
});
"""


@every_csv
def test_report_renders_in_headless_chromium(study, tmp_path):
    from PIL import Image

    out, page = study
    browser = chromium(tmp_path)
    try:
        browser.get(out.as_uri())
        assert browser.execute_script("return document.readyState") == "complete"
        assert browser.title == "clothbench report"
        figures = browser.execute_script(FIGURE_SIZES)
        assert len(figures) == page.count("<svg") >= 10
        empty = [f for f in figures if not (f["width"] > 100 and f["height"] > 100 and f["drawn"] > 0)]
        assert not empty, f"figures without a size or without anything drawn: {empty}"
        errors = [e for e in browser.get_log("browser") if e["level"] in ("SEVERE", "ERROR")]
        assert not errors, errors
        toc = browser.execute_script("return Array.from(document.querySelectorAll('nav.toc a')).map(a => a.hash)")
        missing = [h for h in toc if not browser.execute_script(f"return !!document.getElementById('{h[1:]}')")]
        assert toc and not missing, missing
        shots = [tmp_path / "report-top.png", tmp_path / "report-first-figure.png"]
        assert browser.save_screenshot(str(shots[0]))
        browser.execute_script("document.querySelector('svg').scrollIntoView()")
        assert browser.save_screenshot(str(shots[1]))
        viewport = browser.execute_script("return [window.innerWidth, window.innerHeight]")
    finally:
        browser.quit()
    # the viewport: the window's width, its height less what the window itself takes
    assert viewport[0] == WINDOW[0] and 600 < viewport[1] <= WINDOW[1]
    for shot in shots:
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        with Image.open(shot) as image:
            assert image.size == tuple(viewport)
            assert len(image.convert("L").resize((64, 64)).getcolors(4096)) > 8  # not a blank page
