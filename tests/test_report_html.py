"""report.html opened in headless Chromium (Debian's, driven by selenium) in a 1400-pixel-wide
window: the verdict and the three first plots fill the first screen, every plot decodes, the
console has no errors, every folded section is there with links to its files."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from reports.completion import METRICS, parts_frame, write_completion
from reports.headline import headline_table, write_headline
from reports.html import FIRST_SCREEN, PLOTS
from reports.relations import RELATIONS, pairs_frame, write_relation_report
from reports.run_report import write_run_report
from reports.shapes import GEOMETRY_COLUMNS
from reports.trends import DEFAULT_THRESHOLDS, read_thresholds

CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
FOLDED = ["Inputs that failed, and why", "The run: facts", "Thresholds and the previous run",
          "Shape completion", "Relations", "Assemblies against their CAD mates",
          "Trends over the last runs"]
INSIDE = ["beside the paper's Table II", "beside the paper's Table I",
          "beside the paper's Table III", "Joint type"]
WIDTH, SCREEN = 1400, 1000  # the window, and the first screen the verdict must fit in


def _completion_rows(rng: np.random.Generator) -> list[dict[str, Any]]:
    rows = []
    for k in range(24):
        category = ("fasteners", "linear-rotary-motion")[k % 2]
        for method in ("gan_lstm", "visible", "carve"):
            for protocol in ("observed", "oracle-box"):
                for n_views, view in ((1, 2.88 * (k * 5 % 125)), (2, 0.0)):
                    rows.append({"part_id": f"p{k}-0", "category": category, "split": "test",
                                 "context": "pair", "method": method, "protocol": protocol,
                                 "n_views": n_views, "view_deg": view,
                                 **{m: float(rng.uniform(0.2, 0.9)) for m in METRICS}})
    return rows


def _pair_rows(rng: np.random.Generator) -> list[dict[str, Any]]:
    rows = []
    for scene in ("s0-test-left-00000", "assembly-gear"):
        for view in range(3):
            for inp in ("truth", "partial", "completed"):
                for method in ("ltn", "mlp", "geometric"):
                    for relation in RELATIONS:
                        truth = bool(rng.random() < 0.3)
                        rows.append({
                            "scene": scene, "view": view, "part_a": "p1-0", "part_b": "p2-0",
                            "category": "fasteners", "input": inp, "method": method,
                            "relation": relation, "truth": truth,
                            "predicted": truth if rng.random() < 0.8 else not truth,
                            "confidence": None if method == "geometric" else float(rng.random()),
                            "near_boundary": False, "violation": False})
    return rows


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder written by the stages' own writers, then its report (one earlier run)."""
    rng = np.random.default_rng(0)
    runs = tmp_path_factory.mktemp("runs")
    for name in ("20260101T000000Z", "20260102T000000Z"):
        run = runs / name
        run.mkdir()
        parts = parts_frame(_completion_rows(rng))
        write_completion(run, parts)
        write_headline(run, headline_table(parts, pd.DataFrame(columns=list(GEOMETRY_COLUMNS))))
        joints = pd.DataFrame([{"scene": "assembly-gear", "part_a": "p1-0", "part_b": "p2-0",
                                "kinematic": "revolute"}])
        write_relation_report(run, pairs_frame(_pair_rows(rng)), ["test run"], joints)
        (run / "summary.json").write_text("{}")
    write_run_report(runs / "20260102T000000Z", [runs / "20260101T000000Z"],
                     read_thresholds(DEFAULT_THRESHOLDS), facts={"library": "test"})
    return runs / "20260102T000000Z"


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not (CHROMIUM and DRIVER):
        pytest.skip("Debian's chromium and chromium-driver are not installed "
                    "(scripts/setup.sh --test installs them)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu",
                f"--window-size={WIDTH},{SCREEN}"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    yield driver
    driver.quit()


def test_the_first_screen_is_the_verdict_and_its_three_plots(
        run_dir: Path, browser: Any, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    browser.get((run_dir / "report.html").as_uri())
    assert browser.execute_script("return window.innerWidth") == WIDTH
    shot = tmp_path / "first-screen.png"
    assert browser.save_screenshot(str(shot)) and shot.stat().st_size > 10_000
    table = browser.find_element(By.CSS_SELECTOR, "table#verdict")
    assert _box(browser, table)["bottom"] <= SCREEN
    for name in FIRST_SCREEN:  # the three plots too, whole, side by side
        box = _box(browser, browser.find_element(By.CSS_SELECTOR, f"img[data-plot='{name}']"))
        assert box["bottom"] <= SCREEN and box["width"] > 300, (name, box)
    rows = [r.text.split("\n")[0] for r in table.find_elements(By.CSS_SELECTOR, "tr")[1:]]
    assert [r.split()[0] for r in rows] == ["fasteners", "linear-rotary-motion", "all"]
    cell = table.find_elements(By.CSS_SELECTOR, "tr")[-1].find_elements(By.TAG_NAME, "td")[2]
    assert "floor 0.100" in cell.text and "prev 0." in cell.text  # completion IoU of "all"
    banner = browser.find_element(By.CSS_SELECTOR, "div.banner")
    assert banner.text.startswith("Night 20260102T000000Z:") and "threshold checks" in banner.text


def test_every_plot_decodes_without_console_errors_and_the_tables_are_folded(
        run_dir: Path, browser: Any) -> None:
    from selenium.webdriver.common.by import By

    browser.get((run_dir / "report.html").as_uri())
    severe = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe
    images = {img.get_attribute("data-plot"): img
              for img in browser.find_elements(By.CSS_SELECTOR, "img[data-plot]")}
    assert set(images) == set(PLOTS)
    decoded = browser.execute_async_script(  # waits for every image, folded ones too
        "const done = arguments[arguments.length - 1];"
        "const imgs = [...document.querySelectorAll('img[data-plot]')];"
        "Promise.all(imgs.map(i => i.decode().then(() => [i.dataset.plot, i.naturalWidth])))"
        ".then(done, e => done(String(e)));")
    assert isinstance(decoded, list) and len(decoded) == len(PLOTS), decoded
    for name, width in decoded:
        assert width > 300, name
    folded = browser.find_elements(By.CSS_SELECTOR, "details")
    titles = [d.find_element(By.TAG_NAME, "h2").text for d in folded]
    assert len(titles) == len(FOLDED) and all(map(str.startswith, titles, FOLDED)), titles
    assert not any(d.get_attribute("open") for d in folded)
    assert not any(inside in browser.find_element(By.TAG_NAME, "body").text for inside in INSIDE)
    for summary in browser.find_elements(By.CSS_SELECTOR, "details > summary"):
        links = [a.get_attribute("href") for a in summary.find_elements(By.TAG_NAME, "a")]
        assert links, summary.text
        for link in links:  # every link names a file of the run folder
            assert link.startswith(run_dir.as_uri() + "/") and Path(
                run_dir, link.rsplit("/", 1)[1]).is_file(), link
    browser.execute_script("document.querySelectorAll('details').forEach(d => d.open = true)")
    text = browser.find_element(By.TAG_NAME, "body").text
    for section in INSIDE:
        assert section in text, section
    assert not browser.find_elements(By.CSS_SELECTOR, "script[src], link[href], img[src^=http]")
    sources = [i.get_attribute("src") for i in images.values()]
    assert all(src.startswith("data:image/png;base64,") for src in sources)


def _box(browser: Any, element: Any) -> dict[str, float]:
    """The element's box in the window, pixels, with the page scrolled to the top."""
    return dict(browser.execute_script(
        "window.scrollTo(0, 0); const r = arguments[0].getBoundingClientRect();"
        "return {top: r.top, bottom: r.bottom, width: r.width};", element))


def test_the_report_flags_a_failed_threshold_in_the_page(run_dir: Path, tmp_path: Path,
                                                         browser: Any) -> None:
    strict = tmp_path / "strict.toml"
    strict.write_text("[completion_iou_shapes]\nfloor = 0.99\n")
    run = shutil.copytree(run_dir, tmp_path / run_dir.name)
    report = write_run_report(run, [], read_thresholds(strict))
    assert not report.passed and any("completion_iou_shapes fail" in f for f in report.failed)
    browser.get(Path(report.html).as_uri())
    from selenium.webdriver.common.by import By

    banner = browser.find_element(By.CSS_SELECTOR, "div.banner")
    assert "FAIL" in banner.text and "threshold checks failed" in banner.text
    assert "fail" in banner.get_attribute("class").split()
    failed = browser.find_elements(By.CSS_SELECTOR, "table#verdict td.fail")
    assert failed and any("floor 0.990" in td.text for td in failed)
