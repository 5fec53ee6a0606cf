"""report.html opened in headless Chromium (Debian's, driven by selenium): it renders without
console errors, every plot decodes, every section is there. A screenshot is kept."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from reports.completion import METRICS, parts_frame, write_completion
from reports.html import PLOTS
from reports.relations import RELATIONS, pairs_frame, write_relation_report
from reports.run_report import write_run_report
from reports.trends import DEFAULT_THRESHOLDS, read_thresholds

CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
SECTIONS = ["Thresholds and the previous run", "Shape completion", "beside the paper's Table II",
            "beside the paper's Table I", "Relations", "beside the paper's Table III",
            "Assemblies against their CAD mates", "Joint type", "Trends over the last runs"]


def _completion_rows(rng: np.random.Generator) -> list[dict[str, Any]]:
    rows = []
    for k in range(24):
        category = ("fasteners", "linear-rotary-motion")[k % 2]
        for method in ("gan_lstm", "visible", "carve"):
            for protocol in ("observed", "oracle-box"):
                for n_views, view in ((1, 2.88 * (k * 5 % 125)), (2, 0.0)):
                    rows.append({"part_id": f"p{k}-0", "category": category, "split": "test",
                                 "method": method, "protocol": protocol, "n_views": n_views,
                                 "view_deg": view, **{m: float(rng.uniform(0.2, 0.9))
                                                      for m in METRICS}})
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
        write_completion(run, parts_frame(_completion_rows(rng)))
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
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,3000"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    yield driver
    driver.quit()


def test_the_report_renders_every_plot_without_console_errors(
        run_dir: Path, browser: Any, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    browser.get((run_dir / "report.html").as_uri())
    shot = tmp_path / "report.png"
    assert browser.save_screenshot(str(shot)) and shot.stat().st_size > 10_000
    severe = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe
    images = {img.get_attribute("data-plot"): img
              for img in browser.find_elements(By.CSS_SELECTOR, "img[data-plot]")}
    assert set(images) == set(PLOTS)
    for name, img in images.items():  # decoded, not a broken image
        assert browser.execute_script("return arguments[0].naturalWidth", img) > 100, name
    text = browser.find_element(By.TAG_NAME, "body").text
    for section in SECTIONS:
        assert section in text, section
    assert not browser.find_elements(By.CSS_SELECTOR, "script[src], link[href], img[src^=http]")


def test_the_report_flags_a_failed_threshold_in_the_page(run_dir: Path, tmp_path: Path,
                                                         browser: Any) -> None:
    strict = tmp_path / "strict.toml"
    strict.write_text("[completion_iou]\nfloor = 0.99\n")
    run = shutil.copytree(run_dir, tmp_path / run_dir.name)
    report = write_run_report(run, [], read_thresholds(strict))
    assert not report.passed and any("completion_iou fail" in f for f in report.failed)
    browser.get(Path(report.html).as_uri())
    from selenium.webdriver.common.by import By

    banner = browser.find_element(By.CSS_SELECTOR, "div.banner")
    assert "threshold checks failed" in banner.text and "fail" in banner.get_attribute("class")
    assert browser.find_elements(By.CSS_SELECTOR, "td.fail")
