"""Names from input files never become code or markup: a real STEP assembly whose products a
supplier named with quotes, triple quotes, STEP's ``\\N\\`` newlines, backslashes, terminal
escapes and non-ASCII, in a category folder and under a file name as hostile, goes through
ingest, mates, the reports and the export, and every output keeps the names as data.

The exported CadQuery script is the same code with and without such names (only its JSON data
block differs) and running it does nothing but solve; every other output is checked by a
parser of its format (HTML, Markdown tables, JUnit XML, CSV, the sidecar's JSON, the XBF notes,
Prefect's artifacts, the console), one row of ``OUTPUTS`` each.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from cad_oracle import oracle_record

from cadio.cad.step import read_step
from reports.tables import markdown_text, printable

ROOT = Path(__file__).resolve().parents[1]
ASSEMBLY = "assemblies/abc_00509609_arbor-press.step"  # seven products, coincident mates
MARK = "pwned"  # the file the hostile names try to create

# Product names as a STEP file writes them (ISO 10303-21 escapes: '' a quote, \\ a backslash,
# \N\ a newline, \X\hh a byte, \X2\...\X0\ and \X4\...\X0\ Unicode); @MARK@ is a path.
STEP_NAMES = [
    'plate"""\\N\\open("@MARK@", "w").write("x")\\N\\"""',
    "it''s \\\\ a '''''' quote\\N\\# a comment\\N\\import os; os.remove(\"@MARK@\")",
    "\\X2\\00FC00E9\\X0\\ Zahnrad \\X4\\0001F529\\X0\\ \\X2\\6B6F8ECA\\X0\\",
    "a | b\\N\\| c | d |",
    "<script>alert(1)</script> & <img src=x onerror=alert(2)>",
    "esc \\X\\1B[31mred\\X\\1B[0m \\X2\\202E\\X0\\rtl \\X\\09tab",
    'back\\\\"""\\\\',
]
CATEGORY = 'gears"""|<script>alert(1)\n$\\frac{$ ü \x1b[31m'  # a folder name: no "/"
FILE = 'arbor"""\n\'x\\ ü|<b>'  # the assembly's file name (stem)
BROKEN = "bro|ken\n<img src=x onerror=alert(3)>"  # a truncated file (a failed row)


def _renamed(text: str, names: list[str]) -> str:
    """The STEP text with its products' names and ids replaced, in order of appearance."""
    found = iter(names)

    def rename(m: re.Match[str]) -> str:
        name = next(found)
        return f"PRODUCT( '{name}', '{name}'"

    out, n = re.subn(r"PRODUCT\(\s*'(?:[^']|'')*'\s*,\s*'(?:[^']|'')*'", rename, text)
    assert n == len(names), n
    return out


@pytest.fixture(scope="module")
def marker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the names' code would write if it ever ran (checked absent by every test)."""
    return tmp_path_factory.mktemp("target") / MARK


@pytest.fixture(scope="module")
def hostile_step(shared_step_dir: Path, marker: Path,
                 tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The real arbor press with every product renamed, under a hostile file name."""
    names = [n.replace("@MARK@", str(marker)) for n in STEP_NAMES]
    path = tmp_path_factory.mktemp("hostile") / f"{FILE}.step"
    path.write_text(_renamed((shared_step_dir / ASSEMBLY).read_text(), names))
    return path


def test_the_step_reader_decodes_the_hostile_names(hostile_step: Path) -> None:
    """The names reach the pipeline as a CAD system shows them (newlines, quotes, escapes)."""
    names = [s.info.name for s in read_step(hostile_step)]
    assert len(names) == len(STEP_NAMES) == len(set(names))
    text = "".join(names)
    for needed in ('"""\nopen(', "it's \\ a '''", "ü", "🔩", "\x1b[31m", "\u202e", "\t",
                   "| c |", "<script>", 'back\\"""\\'):
        assert needed in text, needed


# ---------------------------------------------------------------- the CadQuery script


def _script(step: Path, out: Path) -> tuple[Path, list[str]]:
    """The assembly's CadQuery script with the CAD's mates as predictions, and one predicted
    mate that is no constraint (listed with both part names); the file's part names."""
    from cadio.export.script import mass_properties, write_script

    record, solids, _ = oracle_record(step, wrong_concentric=True)
    path = write_script(out / f"{step.stem}_assembly.py", record, step,
                        mass_properties(solids), 0.1, 0.5)
    return path, [s.info.name for s in solids]


BLOCK = re.compile(r'^DATA = json\.loads\(r"""\n(.*)\n"""\)$', re.DOTALL | re.MULTILINE)


def _code_and_data(script: Path) -> tuple[bytes, dict]:
    """The script without the text of its data block, and the data."""
    text = script.read_bytes()
    match = BLOCK.search(text.decode("ascii"))  # ASCII: every other character is escaped
    assert match is not None
    return text[:match.start(1)] + text[match.end(1):], json.loads(match.group(1))


def test_the_script_is_the_same_code_whatever_the_names(
        shared_step_dir: Path, hostile_step: Path, marker: Path, tmp_path: Path) -> None:
    clean_step = tmp_path / "clean" / "arbor-press.step"
    clean_step.parent.mkdir()
    shutil.copy(shared_step_dir / ASSEMBLY, clean_step)
    clean, _ = _script(clean_step, tmp_path / "clean")
    hostile, names = _script(hostile_step, tmp_path / "hostile")
    clean_code, clean_data = _code_and_data(clean)
    hostile_code, data = _code_and_data(hostile)
    assert hostile_code == clean_code
    # the names are all in the data, verbatim; the docstring lists none of them
    assert data["assembly"] == FILE and data["step"] == str(hostile_step)
    assert [p["name"] for p in data["parts"]] == names
    assert data["unconstrained"] and len(data["unconstrained"]) == len(
        clean_data["unconstrained"])
    assert any(n in line for line in data["unconstrained"] for n in names)

    work = tmp_path / "run"  # an empty folder: whatever the script writes shows up here
    work.mkdir()
    out = work / "solved.json"
    run = subprocess.run([sys.executable, str(hostile), "--json", str(out), "--perturb", "1.0"],
                         cwd=work, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    listed = subprocess.run([sys.executable, str(hostile), "--list"], cwd=work,
                            capture_output=True, text=True, timeout=600)
    assert listed.returncode == 0, listed.stderr[-2000:]
    assert not marker.exists() and sorted(work.iterdir()) == [out]
    result = json.loads(out.read_text())
    assert result["reproduced"] and result["constraints_hold"], result
    assert [p["name"] for p in result["parts"]] == names
    placements = {s.info.index: s.info.placement for s in read_step(hostile_step)}
    for part in result["parts"]:  # against the file read again, not the script's copy
        assert np.abs(np.reshape(part["placement"], (4, 4)) - placements[part["index"]]
                      ).max() < 1e-3
    for text in (run.stdout, listed.stdout):  # one line per line printed, nothing that styles
        assert all(c.isprintable() or c == "\n" for c in text), text
    assert len(listed.stdout.splitlines()) == len(data["unconstrained"])


# ---------------------------------------------------------------- every other output


@dataclass(frozen=True)
class Night:
    """What the stages wrote for the hostile library, and what the console showed."""

    library: Path
    workspace: Path
    run_dir: Path
    names: list[str]       # the assembly's part names, as read
    broken: Path           # the truncated file
    ingest_console: str
    export_console: str
    report: object         # reports.run_report.RunReport


def _mateqa(*args: str) -> str:
    proc = subprocess.run([sys.executable, "-m", "flows.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.fixture(scope="module")
def night(hostile_step: Path, box_step: Path,
          tmp_path_factory: pytest.TempPathFactory) -> Night:
    """ingest (the command line), mates, the ingest, stage and run reports, and the export
    (the command line) of a library holding the hostile assembly, a truncated file with a
    hostile name beside it, and a plain part in another category."""
    from cadio.catalog import read_catalog
    from cadio.truth.assemblies import assembly_jobs, extract_assembly_mates
    from cadio.workspace import Workspace
    from reports.render import (
        build_ingest_report,
        build_stage_report,
        write_ingest_report,
        write_stage_report,
    )
    from reports.run_report import write_run_report
    from reports.trends import read_thresholds

    root = tmp_path_factory.mktemp("night")
    lib, ws = root / "library", Workspace(root / "ws")
    (lib / CATEGORY).mkdir(parents=True)
    (lib / "fasteners").mkdir()
    shutil.copy(hostile_step, lib / CATEGORY / hostile_step.name)
    broken = lib / CATEGORY / f"{BROKEN}.stp"
    broken.write_bytes(hostile_step.read_bytes()[:3000])
    shutil.copy(box_step, lib / "fasteners" / "box.step")
    ingest_console = _mateqa("ingest", str(lib), "--workspace", str(ws.root),
                             "--voxel-sizes", "16")
    catalog = read_catalog(ws.catalog)
    mates = list(extract_assembly_mates(assembly_jobs(catalog, ws.root)))
    assert [m.status for m in mates] == ["ok"]
    run_dir = ws.run_dir("20260101T000000000000Z")
    write_ingest_report(run_dir, build_ingest_report(catalog))
    write_stage_report(run_dir, build_stage_report(mates, None, []))
    limits = root / "thresholds.toml"  # every check counts: the hostile category fails one
    limits.write_text("min_n = 1\n\n[ingest_ok_fraction]\nfloor = 0.9\n")
    report = write_run_report(run_dir, [], read_thresholds(limits), ws.catalog,
                              {"library": str(lib)})
    # the run completed as far as the export is concerned: a night writes summary.json last
    (run_dir / "summary.json").write_text(json.dumps({"run_dir": str(run_dir)}))
    export_console = _mateqa("export", "--workspace", str(ws.root), "--run", run_dir.name)
    names = [s.info.name for s in read_step(hostile_step)]
    return Night(lib, ws.root, run_dir, names, broken, ingest_console, export_console, report)


class _Page(HTMLParser):
    """Every tag, attribute and text of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, list[tuple[str, str | None]]]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, attrs))

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def _html(n: Night) -> None:
    page = _Page()
    page.feed((n.run_dir / "report.html").read_text())
    assert "script" not in {t for t, _ in page.tags}
    assert not [a for _, attrs in page.tags for a, _ in attrs if a.startswith("on")]
    text = "".join(page.text)  # the names are shown, as text (pandas writes "\n" as \n)
    for name in (CATEGORY, str(n.broken)):
        assert name.replace("\n", "\\n") in text, name


def _plot(n: Night) -> None:
    """A plot whose labels are the hostile category ("$" starts mathtext in matplotlib)."""
    from reports.html import Page
    from reports.plots import category_iou

    table = pd.DataFrame({"category": [CATEGORY, "fasteners"], "method": "gan_lstm",
                          "iou": [0.5, 0.6]})
    page = Page("plot")
    page.plot("category_iou", "IoU per category", lambda fig: category_iou(fig, table))
    assert "data-plot='category_iou'" in page.render()


def _cells(row: str) -> list[str]:
    return re.split(r"(?<!\\)\|", row.strip())[1:-1]


def _markdown(name: str) -> Callable[[Night], None]:
    def check(n: Night) -> None:
        text = (n.run_dir / name).read_text()
        assert all(c.isprintable() or c == "\n" for c in text)
        assert "<" not in text.replace("&lt;", "")  # no raw HTML for a renderer to run
        assert markdown_text(CATEGORY) in text
        tables: list[list[str]] = []
        for line in text.splitlines():
            if line.startswith("|"):
                tables[-1:] = [tables[-1] + [line]] if tables and tables[-1] else [[line]]
            elif tables and tables[-1]:
                tables.append([])
        for rows in filter(None, tables):  # every row has the header's cells
            assert {len(_cells(r)) for r in rows} == {len(_cells(rows[0]))}, rows
    return check


def _junit(n: Night) -> None:
    root = ET.parse(n.run_dir / "junit.xml").getroot()  # well-formed XML, names and all
    classes = {case.get("classname") for case in root.iter("testcase")}
    assert CATEGORY.replace("\x1b", "\\x1b") in classes  # XML cannot hold ESC, even escaped
    failed = [c for c in root.iter("testcase") if c.find("failure") is not None]
    assert {c.get("classname") for c in failed} == {CATEGORY.replace("\x1b", "\\x1b"), "all"}


def _csv(n: Night) -> None:
    checks = pd.read_csv(n.run_dir / "categories.csv")
    assert CATEGORY in set(checks["category"])
    index = pd.read_csv(n.run_dir / "exports" / "index.csv")
    assert list(index["assembly"]) == [FILE]


def _sidecar(n: Night) -> None:
    from cadio.export.sidecar import read_sidecar

    doc = read_sidecar(n.run_dir / "exports" / FILE / f"{FILE}.mates.json")
    assert doc["assembly"] == FILE and doc["category"] == CATEGORY
    assert [p["name"] for p in doc["parts"]] == n.names


def _notes(n: Night) -> None:
    from cadio.export.notes import read_notes

    notes = [note.data for note in read_notes(n.run_dir / "exports" / FILE / f"{FILE}.xbf")]
    assert [d["part"]["name"] for d in notes if d["kind"] == "part"] == n.names
    assert {d["a"]["name"] for d in notes if d["kind"] == "pair"} <= set(n.names)


def _exported_script(n: Night) -> None:
    script = n.run_dir / "exports" / FILE / f"{FILE}_assembly.py"
    _code, data = _code_and_data(script)
    assert [p["name"] for p in data["parts"]] == n.names
    assert data["unconstrained"]  # the pairs not captured, named: in the data only


def _console(n: Night) -> None:
    for text in (n.ingest_console, n.export_console):
        assert all(c.isprintable() or c == "\n" for c in text), text
    assert markdown_text(CATEGORY) in n.ingest_console
    assert f"{printable(FILE)}: no-predictions" in n.export_console.splitlines()[-2]


def _artifacts(n: Night) -> None:
    """What the flow publishes: the checks table as JSON rows, the report as Markdown."""
    rows = n.report.table_rows()  # type: ignore[attr-defined]
    assert json.loads(json.dumps(rows)) == rows
    assert CATEGORY in {r["category"] for r in rows}
    assert n.report.markdown == (n.run_dir / "report.md").read_text()  # type: ignore[attr-defined]


OUTPUTS: dict[str, Callable[[Night], None]] = {
    "report.html": _html,
    "report.html plots": _plot,
    "report.md": _markdown("report.md"),
    "ingest.md": _markdown("ingest.md"),
    "stages.md": _markdown("stages.md"),
    "junit.xml": _junit,
    "categories.csv and index.csv": _csv,
    "sidecar JSON": _sidecar,
    "XBF notes": _notes,
    "exported script": _exported_script,
    "console": _console,
    "Prefect artifacts": _artifacts,
}


@pytest.mark.parametrize("output", list(OUTPUTS))
def test_every_output_keeps_hostile_names_as_data(output: str, night: Night,
                                                  marker: Path) -> None:
    OUTPUTS[output](night)
    assert not marker.exists()


@pytest.mark.server
def test_prefect_artifacts_carry_the_names_as_published(night: Night,
                                                       prefect_api: dict[str, str]) -> None:
    """The artifacts read back from a real Prefect server are the report's, names intact."""
    from prefect import flow
    from prefect.artifacts import Artifact

    from flows.nightly import publish

    @flow
    def published() -> None:
        publish(night.report)  # type: ignore[arg-type]

    from conftest import served_by

    with served_by(prefect_api):
        published()
        table = Artifact.get("nightly-categories")
        markdown = Artifact.get("nightly-report")
    assert table is not None and markdown is not None
    rows = json.loads(table.data) if isinstance(table.data, str) else table.data
    assert CATEGORY in {r["category"] for r in rows}
    assert markdown.data == (night.run_dir / "report.md").read_text()
