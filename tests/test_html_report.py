"""The interactive HTML report: metrics in every report, and report.html in a real headless Chromium.

The browser tests drive Debian's ``chromium`` (``apt-get install chromium``; .ci/run installs it)
through the Python ``playwright`` package with ``executable_path``: no browser download.
They skip with the reason when either is missing.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import shutil

import numpy as np
import pytest

from mcrecon.cli import main
from mcrecon.experiments import convergence as conv
from mcrecon.experiments.convergence import run_convergence
from mcrecon.core.metrics import flip_available

SIZE = (24, 16)  # not square: catches a width/height swap
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def _chromium() -> str | None:
    for path in (os.environ.get("MCRECON_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium")):
        if path and os.path.isfile(path) and os.access(path, os.X_OK):
            return path
    return None


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("html-report")
    res = run_convergence("soft_shadow", methods=["box", "gem"], spp=[2, 4], size=SIZE, oidn=False, out=out,
                          html=True)
    return out, res


def _layers(html_text):
    m = re.search(r'<script type="application/json" id="report-data">(.*?)</script>', html_text, re.S)
    return json.loads(m.group(1).replace("<\\/", "</"))["layers"]


# ---- without a browser ---------------------------------------------------------------------------------------------

def test_every_metric_in_every_report(report):
    out, res = report
    keys = ("relative_mse", "smape", "one_minus_ssim", "rmse", "ssim") + (("flip",) if flip_available() else ())
    for r in res.rows:
        assert all(math.isfinite(r[k]) for k in keys), r
        assert r["one_minus_ssim"] == pytest.approx(1 - r["ssim"])
        assert ("flip" in r) == flip_available()
    md = (out / "report.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| method |"))
    for col in ("relative MSE", "SMAPE", "1−SSIM", "RMSE"):
        assert col in header
    assert ("FLIP" in header) == flip_available()
    assert "ε = 0.01" in md and "[report.html](report.html)" in md
    page = (out / "report.html").read_text()
    for col in ("relMSE", "SMAPE", "1−SSIM", "toolkit s"):
        assert f">{col}</th>" in page
    assert (">FLIP</th>" in page) == flip_available()


def test_html_is_self_contained(report):
    out, res = report
    page = (out / "report.html").read_text()
    # every src/href is an embedded data: URI or an in-page anchor; no http(s) anywhere
    refs = re.findall(r'(?:src|href)\s*=\s*"([^"]*)"', page)
    assert refs and all(r.startswith(("data:", "#")) for r in refs), [r[:40] for r in refs if not r.startswith("data:")]
    assert "http://" not in page and "https://" not in page
    layers = _layers(page)
    ids = [la["id"] for la in layers]
    # reference, then the box image, then the other methods; the noisy input duplicates box (uniform)
    assert ids[:2] == ["reference", "box_uniform"]
    assert set(ids) == {"reference", "box_uniform", "gem_uniform", "gem_adaptive"}
    for la in layers:
        assert la["image"].startswith("data:image/png;base64,")
        assert (la["error"] is None) == (la["id"] == "reference")
        assert (la["density"] is not None) == (la["id"] == "gem_adaptive")


def test_cli_html_and_gallery(tmp_path, capsys):
    code = main(["experiment", "convergence", "--scene", "flat", "--spp", "2", "--size", "12x8", "--methods", "box",
                 "--modes", "uniform", "--oidn", "no", "--flip", "no", "--html", "--out", str(tmp_path / "c")])
    assert code == 0
    assert "report.html" in capsys.readouterr().out
    assert (tmp_path / "c" / "report.html").stat().st_size > 0
    assert "FLIP: not computed" in (tmp_path / "c" / "report.md").read_text()
    code = main(["experiment", "gallery", "--scenes", "flat", "--methods", "box", "--size", "12x8", "--spp", "2",
                 "--html", "--out", str(tmp_path / "g")])
    assert code == 0
    md = (tmp_path / "g" / "gallery.md").read_text()
    assert "(gallery/flat.html)" in md and "SMAPE" in md and "1−SSIM" in md
    assert _layers((tmp_path / "g" / "gallery" / "flat.html").read_text())[0]["id"] == "reference"


def test_report_command_rebuilds_the_page_from_the_run_folder(report, tmp_path, capsys):
    from mcrecon.cli import main

    out, res = report
    assert main(["report", str(out), "-o", str(tmp_path / "again.html")]) == 0
    fresh = _layers((out / "report.html").read_text())
    again = _layers((tmp_path / "again.html").read_text())
    # the same layers, labels, sample-density maps and error means (the run folder keeps float32 EXRs:
    # the error means agree to float32 rounding of the images)
    assert [(la["id"], la["label"], la["density"] is None) for la in again] == \
        [(la["id"], la["label"], la["density"] is None) for la in fresh]
    for a, b in zip(again, fresh):
        if b.get("error_mean") is not None:
            assert a["error_mean"] == pytest.approx(b["error_mean"], rel=1e-5)
    capsys.readouterr()
    assert main(["report", str(tmp_path), "-o", str(tmp_path / "x.html")]) == 2  # not a run folder
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "convergence.json" in err and "does not exist" in err
    assert main(["report", str(out), "-o", str(tmp_path / "x.png")]) == 2
    assert ".html" in capsys.readouterr().err


def test_flip_left_out_with_a_note_when_not_installed(tmp_path, monkeypatch):
    monkeypatch.setattr(conv, "flip_available", lambda: False)
    res = run_convergence("flat", methods=["box"], spp=[2], size=(8, 8), modes=["uniform"], oidn=False,
                          out=tmp_path, html=True)
    assert not res.flip and all("flip" not in r for r in res.rows)
    assert any("flip-evaluator" in n for n in res.notes)
    assert "pip install flip-evaluator" in (tmp_path / "report.md").read_text()
    assert "pip install flip-evaluator" in (tmp_path / "report.html").read_text()
    with pytest.raises(Exception, match="flip-evaluator"):
        run_convergence("flat", methods=["box"], spp=[2], size=(8, 8), modes=["uniform"], oidn=False, flip=True)


# ---- in a real headless Chromium ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def browser():
    path = _chromium()
    if path is None:
        pytest.skip("chromium is not installed (apt-get install chromium; .ci/run installs it): "
                    "the HTML report's browser tests need it")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the browser tests need playwright "
                                   "(pip install playwright; no browser download: Debian's chromium is used)")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=path, args=CHROMIUM_ARGS, headless=True)
        yield b
        b.close()


@pytest.fixture
def page(browser, report):
    out, _ = report
    pg = browser.new_page(viewport={"width": 1100, "height": 1000})
    errors, requests = [], []
    pg.on("console", lambda m: errors.append(f"console error: {m.text}") if m.type == "error" else None)
    pg.on("pageerror", lambda e: errors.append(f"page error: {e}"))
    pg.on("request", lambda r: requests.append(r.url))
    pg.goto((out / "report.html").as_uri())
    pg.wait_for_selector("body[data-ready='1']", timeout=10_000)
    pg.errors = errors
    pg.requests = requests
    yield pg
    pg.close()


def _transform(pg):
    return pg.eval_on_selector("#stage", "e => e.style.transform")


def _scale_translate(t):
    m = re.fullmatch(r"translate\(([-\d.e]+)px, ([-\d.e]+)px\) scale\(([-\d.e]+)\)", t)
    assert m, t
    return float(m.group(3)), float(m.group(1)), float(m.group(2))


def _png(data):
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.float64)


def test_viewer_flip_zoom_pan_exposure_error_map(page):
    img = page.locator("#view")
    assert img.get_attribute("data-layer") == "reference" and img.get_attribute("data-view") == "image"
    src_ref = img.get_attribute("src")
    assert src_ref.startswith("data:image/png")

    # flip with key 2: the box image, a different picture
    page.keyboard.press("2")
    assert img.get_attribute("data-layer") == "box_uniform"
    assert img.get_attribute("src") != src_ref

    # wheel zoom about the viewport centre: the transform changes, the scale grows
    vp = page.locator("#viewport").bounding_box()
    cx, cy = vp["x"] + vp["width"] / 2, vp["y"] + vp["height"] / 2
    page.mouse.move(cx, cy)
    t0 = _transform(page)
    page.mouse.wheel(0, -240)
    page.wait_for_function("t => document.getElementById('stage').style.transform !== t", arg=t0, timeout=5000)
    t1 = _transform(page)
    assert _scale_translate(t1)[0] > _scale_translate(t0)[0]

    # flipping keeps zoom and pan
    page.keyboard.press("3")
    assert img.get_attribute("data-layer") not in ("reference", "box_uniform")
    assert _transform(page) == t1
    page.keyboard.press("Space")  # back to the previous layer
    assert img.get_attribute("data-layer") == "box_uniform"

    # drag pans by the mouse's displacement, same scale
    page.mouse.down()
    page.mouse.move(cx + 40, cy + 25, steps=4)
    page.mouse.up()
    s1, x1, y1 = _scale_translate(t1)
    s2, x2, y2 = _scale_translate(_transform(page))
    assert s2 == s1 and x2 - x1 == pytest.approx(40, abs=0.5) and y2 - y1 == pytest.approx(25, abs=0.5)

    # exposure: slider and keys set a CSS brightness on the image
    page.locator("#exposure").fill("2")
    assert img.evaluate("e => e.style.filter") == f"brightness({2 ** (2 / 2.2):.4f})"
    page.keyboard.press("-")
    assert page.locator("#ev").text_content() == "+1.50 EV"

    # error map of the current method; the reference has none and shows its image
    layers = {la["id"]: la for la in page.evaluate("JSON.parse(document.getElementById('report-data').textContent)"
                                                    ".layers")}
    page.keyboard.press("e")
    assert img.get_attribute("data-view") == "error"
    assert img.get_attribute("src") == layers["box_uniform"]["error"]
    assert img.evaluate("e => e.style.filter") == "none"  # no exposure on false colour
    page.keyboard.press("1")
    assert img.get_attribute("data-layer") == "reference" and img.get_attribute("data-view") == "image"

    # a click on a metrics row shows that method
    page.locator("#metrics tr[data-layer='gem_adaptive']").click()
    assert img.get_attribute("data-layer") == "gem_adaptive"
    page.keyboard.press("d")
    assert img.get_attribute("src") == layers["gem_adaptive"]["density"]

    assert not page.errors, page.errors
    assert all(u.startswith(("file:", "data:")) for u in page.requests), page.requests


def test_screenshot_shows_pixelated_image(page, report):
    _, res = report
    page.keyboard.press("f")  # fit: integer zoom, whole image in view
    s, _, _ = _scale_translate(_transform(page))
    assert s == int(s) and s >= 8
    img = page.locator("#view")
    shot = _png(img.screenshot())
    assert shot.var() > 0, "blank screenshot"
    w, h = SIZE
    s = int(s)
    # the element's box may sit at a fractional CSS position: the shot can have one extra row/column
    assert h * s <= shot.shape[0] <= h * s + 1 and w * s <= shot.shape[1] <= w * s + 1, shot.shape
    shot = shot[:h * s, :w * s]
    # nearest-neighbour zoom: every image pixel is a flat s x s block (inner part, away from the block edges)
    blocks = shot.reshape(h, s, w, s, 3)[:, 2:-2, :, 2:-2]
    assert np.ptp(blocks, axis=(1, 3)).max() <= 2
    # and its centres are the PNG preview of the reference
    from mcrecon.core.display import tonemap_srgb

    want = np.round(tonemap_srgb(res.reference) * 255)
    assert np.abs(shot[s // 2::s, s // 2::s] - want).max() <= 2
    page.keyboard.press("2")
    assert np.abs(_png(img.screenshot())[:h * s, :w * s] - shot).max() > 0, "flipping did not change the pixels"
    full = _png(page.screenshot(full_page=True))
    assert full.var() > 0
    assert not page.errors, page.errors


@pytest.mark.parametrize("height", [1000, 700])
def test_opened_page_shows_the_whole_image_and_its_caption_in_the_window(browser, report, height):
    """No scrolling to see the picture: the viewer comes before the tables, and its viewport takes the
    window's height below it (at most 512 px), the fitted image inside it."""
    out, _ = report
    pg = browser.new_page(viewport={"width": 1280, "height": height})
    pg.goto((out / "report.html").as_uri())
    pg.wait_for_selector("body[data-ready='1']", timeout=10_000)
    vp, img = pg.locator("#viewport").bounding_box(), pg.locator("#view").bounding_box()
    caption = pg.locator("#caption").bounding_box()
    assert vp["y"] + vp["height"] <= caption["y"] + 1 and caption["y"] + caption["height"] <= height
    assert vp["y"] - 1 <= img["y"] and img["y"] + img["height"] <= vp["y"] + vp["height"] + 1
    assert img["height"] >= 16 * 8  # still a useful zoom (8x) of the 24x16 film
    pg.close()
