"""report.html: its content, and a real headless Chromium loading it with no console errors and every figure
decoded (driven over the DevTools protocol with a small stdlib websocket client). Needs Debian's
`chromium` package; skipped with a message without it."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
from _chromium import Browser, chromium_path

from saft.export import report_command
from saft.export.report import write_report

SECTIONS = ["summary", "losses", "metrics", "params", "maps", "renders", "depth", "timings", "config"]


@pytest.fixture(scope="module")
def full_report(shared_result_dir) -> Path:
    """One report of a result with every optional part, shared by the content and browser checks."""
    out = report_command(shared_result_dir)
    assert out == shared_result_dir / "report.html"
    return out


def test_report_content(full_report):
    text = full_report.read_text()
    for sid in SECTIONS:
        assert f'<section id="{sid}">' in text
    assert '<p class="none">' not in text  # every section has its data in this result
    # self-contained: no external resources of any kind
    assert not re.search(r'(src|href)="(?!data:|#)', text)
    assert "http://" not in text and "https://" not in text
    assert text.count('<img src="data:image/png;base64,') == 14
    assert "wave &lt;test&gt; &amp; co" in text  # config shown, HTML-escaped
    assert "constant_acceleration" in text and "substeps" in text
    assert "12.25 s" in text
    assert "cd2_1e-4m2 (1e-4 m^2)" in text and "num_gt_points" not in text  # units shown, counts not plotted


def test_metrics_series_formats():
    from saft.export.figures import metrics_series

    records = {"per_frame": [{"frame": 2, "CD2": 1.0, "note": "x"}, {"frame": 3, "CD2": 2.0}], "mean": {"CD2": 1.5}}
    series, means = metrics_series(records)
    assert list(series) == ["CD2"] and series["CD2"][0].tolist() == [2.0, 3.0] and means == {"CD2": 1.5}
    lists = {"per_frame": {"cd1_cm": [1.0, float("nan"), 3.0]}, "units": {"cd1_cm": "cm"}}
    series, means = metrics_series(lists)
    assert series["cd1_cm (cm)"][0].tolist() == [0.0, 2.0] and means == {}


def test_report_without_optional_parts(bare_result_dir, tmp_path):
    out = write_report(bare_result_dir, tmp_path / "sub" / "r.html")
    text = out.read_text()
    assert "no metrics.json" in text and "no depth ground truth" in text
    assert "material/" not in text.split('id="maps"')[1].split("</section>")[0]
    assert text.count("<img ") == 5  # 2 loss phases, texture, contact sheet, timings


def test_report_minimal_result(bare_result_dir, tmp_path):
    for name in ("log.csv", "timings.json", "config.toml", "texture.png"):
        (bare_result_dir / name).unlink()
    shutil.rmtree(bare_result_dir / "renders")
    text = write_report(bare_result_dir).read_text()
    for msg in ("no log.csv", "no timings.json", "no config.toml", "no renders/", "no texture.png"):
        assert msg in text


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    exe = chromium_path()
    if exe is None:
        pytest.skip("chromium not installed (Debian: apt-get install -y chromium): the headless-browser check "
                    "of report.html is skipped")
    b = Browser(exe, tmp_path_factory.mktemp("chromium"))
    yield b
    b.close()


def test_report_in_headless_chromium(browser, full_report):
    info, errors = browser.open(full_report)
    assert errors == []
    assert info["title"].startswith("saft report")
    assert info["sections"] == SECTIONS
    assert info["figures"] == len(info["images"]) == 14
    bad = [i for i, (complete, w, h) in enumerate(info["images"]) if not (complete and w > 0 and h > 0)]
    assert bad == [], f"images that did not decode: {bad}"


def test_browser_check_sees_errors(browser, tmp_path):
    """The harness itself: a page with a broken image and a console error is caught."""
    page = tmp_path / "broken.html"
    page.write_text('<!DOCTYPE html><html><head><link rel="icon" href="data:,"></head><body>'
                    '<img src="data:image/png;base64,AAAA"><script>console.error("boom")</script></body></html>')
    info, errors = browser.open(page)
    assert any("boom" in e for e in errors)
    assert info["images"][0][1] == 0
