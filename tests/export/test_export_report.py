"""report.html: its content, and a real headless Chromium loading it with no console errors and every figure
decoded (driven over the DevTools protocol with a small stdlib websocket client). Needs Debian's
`chromium` package; skipped with a message without it."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from _chromium import Browser, chromium_path

from saft.export import report_command
from saft.export.report import write_report

SECTIONS = ["summary", "losses", "metrics", "params", "maps", "renders", "novel", "depth", "timings", "config"]
N_IMAGES = 13   # 2 loss phases, metrics, 5 maps, 2 comparison figures, the novel-view strip, depth, timings


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
    assert text.count('<img src="data:image/png;base64,') == N_IMAGES
    assert text.count('<video id="video-') == 2 and text.count('src="data:video/mp4;base64,') == 2
    assert "<h1>saft reconstruction: wave</h1>" in text and "25 fps (frame_dt 0.04 s)" in text
    assert "wave &lt;test&gt; &amp; co" in text  # config shown, HTML-escaped
    assert "12.25 s" in text
    # metric names once, readable, with their units; counts not shown
    assert "<td>CD2 (10⁻⁴ m²)</td>" in text and "<td>p2s (mm)</td>" in text
    assert "cd2_1e-4m2" not in text and "num_gt_points" not in text
    # every parameter with its unit
    params = text.split('<section id="params">')[1].split("</section>")[0]
    for name, unit in (("Y", "N/m"), ("B", "N·m/rad²"), ("log10_Y", "log₁₀(Y / (N/m))"), ("constant_acceleration", "m/s²"),
                       ("damping", "1 (velocity factor per substep)"), ("frame_dt", "s"), ("substeps", "per video frame")):
        assert re.search(rf"<td>{re.escape(name)}</td><td class=\"num\">[^<]*</td><td>{re.escape(unit)}</td>", params), name
    assert "<td>—</td>" not in params
    # a = (0, 9.7, 0.1) against the scene's g = (0, 9.81, 0): 0.59° apart, 0.9888 of its magnitude
    assert "angle between a and g (°)</td><td class=\"num\">0.590657<" in params
    assert "|a| / |g|</td><td class=\"num\">0.988839<" in params
    renders = text.split('<section id="renders">')[1].split("</section>")[0]
    assert "mean PSNR (dB)" in renders and "none held out" in renders and "Held-out frames: none" in renders
    assert "at the scene's 25 fps (0.24 s)" in renders


def test_metrics_series_formats():
    from saft.export.figures import metrics_series

    records = {"per_frame": [{"frame": 2, "CD2": 1.0, "note": "x"}, {"frame": 3, "CD2": 2.0}], "mean": {"CD2": 1.5}}
    series, means = metrics_series(records)
    assert list(series) == ["CD2"] and series["CD2"][0].tolist() == [2.0, 3.0] and means == {"CD2": 1.5}
    lists = {"per_frame": {"cd1_cm": [1.0, float("nan"), 3.0]}, "units": {"cd1_cm": "cm"}}
    series, means = metrics_series(lists)
    assert series["CD1 (cm)"][0].tolist() == [0.0, 2.0] and means == {}
    other = {"per_frame": {"custom_m": [1.0]}, "units": {"custom_m": "m"}}
    assert list(metrics_series(other)[0]) == ["custom_m (m)"]


def test_report_without_optional_parts(bare_result_dir, tmp_path):
    out = write_report(bare_result_dir, tmp_path / "sub" / "r.html")
    text = out.read_text()
    assert "no metrics.json" in text and "no depth ground truth" in text
    assert "material/" not in text.split('id="maps"')[1].split("</section>")[0]
    assert text.count("<img ") == 5  # 2 loss phases, texture, comparison figure, timings
    assert "no material/novel_view/" in text and text.count("<video ") == 1


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
    assert info["figures"] == len(info["images"]) == N_IMAGES
    bad = [i for i, (complete, w, h) in enumerate(info["images"]) if not (complete and w > 0 and h > 0)]
    assert bad == [], f"images that did not decode: {bad}"
    # the embedded comparison videos play: decoded, 6 frames at the scene's 25 fps
    videos = json.loads(browser.evaluate(
        "Promise.all(Array.from(document.querySelectorAll('video')).map(v => new Promise(ok => {"
        " const done = () => ok([v.readyState, v.duration, v.videoWidth, v.error ? v.error.code : 0]);"
        " if (v.readyState >= 2) done(); else { v.addEventListener('loadeddata', done);"
        " v.addEventListener('error', done); } }))).then(JSON.stringify)"))
    assert len(videos) == 2
    for ready, duration, width, err in videos:
        assert err == 0 and ready >= 2 and width > 0 and abs(duration - 6 / 25) < 0.05, videos
    assert browser.evaluate("document.querySelectorAll('.speed button').length") == 6
    # what the reader sees: the difference panels in colour (the colour map), labelled, with the colour bar
    shot = _element_shot(browser, "#renders figure img")
    saturated = (shot.max(axis=2).astype(int) - shot.min(axis=2)) > 120
    assert shot.std() > 20 and saturated.mean() > 0.01
    strip = _element_shot(browser, "#novel figure img")
    assert strip.shape[1] > 3 * strip.shape[0]  # a strip: frames side by side


def _element_shot(browser, selector: str):
    """A screenshot of the first element matching `selector`."""
    box = json.loads(browser.evaluate(
        f"(() => {{ const r = document.querySelector('{selector}').getBoundingClientRect();"
        " return JSON.stringify({x: r.x + window.scrollX, y: r.y + window.scrollY, width: r.width,"
        " height: r.height}); })()"))
    return browser.screenshot(box)


def test_browser_check_sees_errors(browser, tmp_path):
    """The harness itself: a page with a broken image and a console error is caught."""
    page = tmp_path / "broken.html"
    page.write_text('<!DOCTYPE html><html><head><link rel="icon" href="data:,"></head><body>'
                    '<img src="data:image/png;base64,AAAA"><script>console.error("boom")</script></body></html>')
    info, errors = browser.open(page)
    assert any("boom" in e for e in errors)
    assert info["images"][0][1] == 0


def test_report_shows_maps_beside_their_ground_truth(bare_result_dir, tmp_path):
    """With appearance metrics from saft evaluate, the report has the section: the table of phase 3 against
    the texture-only baseline and one estimate | truth | |error| figure per map."""
    from saft.appearance.config import cpu_profile
    from saft.appearance.fit import AppearanceResult, save_appearance
    from saft.evaluate.appearance import read_appearance_ground_truth
    from saft.evaluate.appearance_result import evaluate_appearance_result
    from saft.synthetic.appearance import AppearanceSceneSpec, write_appearance_scene

    spec = AppearanceSceneSpec(fabric="satin", frames=2, width=40, height=30, spp=4, map_size=32, grid=5,
                               env_height=8, env_width=16)
    scene = write_appearance_scene(tmp_path / "scene", spec)
    gt = read_appearance_ground_truth(scene)
    res = AppearanceResult(gt.base_color * 0.5, gt.roughness * 0 + 0.5, gt.metallic, gt.env_video, [], cpu_profile(),
                           materials=[{"cluster": 0, "area": 1.0, "determined": False}])
    save_appearance(res, bare_result_dir)
    assert evaluate_appearance_result(bare_result_dir, scene, spp=4) is not None
    text = write_report(bare_result_dir, tmp_path / "r.html").read_text()
    section = text.split('<section id="appearance">')[1].split("</section>")[0]
    assert "<td>roughness_mae</td>" in section and "texture only" in section
    assert section.count("estimate | truth | |error|</figcaption>") == 3
    assert "showed no specular evidence" in text.split('<section id="maps">')[1].split("</section>")[0]
