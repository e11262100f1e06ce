"""The calibration report page (`calibkit wand` writes NAME.report.html) opened in headless
Chromium: one self-contained file that renders offline, with the figures of --json."""

from __future__ import annotations

import contextlib
import io
import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from browser import CHROMIUM, Browser

from calibkit.core.camera import Rig

needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium "
                                   "package (.ci/run installs it)")


def _cli(*args) -> tuple[int, str]:
    """`calibkit ARGS` run in this process, as conftest's calibkit_cli does (a module
    fixture cannot take its capsys): the exit code and stderr. In-process because each
    `python -m calibkit.cli` paid the imports again (about 4 s of a 5 s wand run)."""
    from calibkit.cli import app
    from calibkit.clitools import run_app

    err, old = io.StringIO(), sys.argv
    sys.argv = ["calibkit", *map(str, args)]
    code = 0
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            run_app(app, "calibkit")
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = old
    return code, err.getvalue()


@pytest.fixture(scope="module")
def wand_run(tmp_path_factory):
    """A simulated wand dance calibrated from exact intrinsics: rig, JSON and report."""
    tmp = tmp_path_factory.mktemp("report")
    truth, csv = tmp / "true.toml", tmp / "wand.csv"
    assert _cli("sim", "rig", "--out", truth, "--cameras", "4", "--seed", "5")[0] == 0
    assert _cli("sim", "wand", "--rig", truth, "--out", csv, "--frames", "300",
                "--noise-px", "0.2", "--seed", "5")[0] == 0
    out = tmp / "rig.toml"
    code, err = _cli("wand", "--from", csv, "--intrinsics", truth, "--fix-intrinsics",
                     "--out", out, "--json", tmp / "w.json")
    assert code == 0, err
    return {"dir": tmp, "rig": out, "json": json.loads((tmp / "w.json").read_text()),
            "page": tmp / "rig.report.html"}


@pytest.fixture(scope="module")
def browser():
    """One Chromium for the module's pages (each start costs seconds); each test loads
    its own page with _show, which also forgets the events of the pages before."""
    if CHROMIUM is None:
        pytest.skip("needs Debian's chromium package (.ci/run installs it)")
    b = Browser(1200, 900)
    b.call("Network.enable")
    try:
        yield b
    finally:
        b.close()


def _show(b: Browser, page: Path, timeout_s: float = 60.0) -> None:
    """Load the page and wait until it is the document evaluated: Page.navigate answers
    before the document before it (another report, complete with its own images) is
    gone, and an evaluation landing while they are swapped fails with "Inspected target
    navigated or closed", a not-yet here."""
    url = page.as_uri()
    b.events.clear()
    b.open(url)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if b.js(f"location.href === {url!r} && document.readyState === 'complete'"):
                return
        except RuntimeError as e:
            if "navigated or closed" not in str(e):
                raise
        time.sleep(0.05)
    raise AssertionError(f"{url} did not load in {timeout_s} s")


def test_report_is_written_beside_the_rig_and_holds_everything(wand_run):
    text = wand_run["page"].read_text()
    # self-contained: no address outside the page (images are data URIs, no scripts)
    assert "http://" not in text.replace('xmlns="http://www.w3.org/2000/svg"', "")
    assert "https://" not in text and "<script" not in text
    assert text.count("data:image/png;base64,") == 3  # layout, residuals, coverage
    rig = Rig.load(wand_run["rig"])
    assert text.count('class="frustum"') == 2 * len(rig)  # from above and from the side


@needs_browser
def test_report_renders_in_a_browser_with_the_json_figures(wand_run, browser):
    report = wand_run["json"]
    b = browser
    _show(b, wand_run["page"])
    assert b.wait_for("document.readyState === 'complete' && document.images.length === 3"
                      " && [...document.images].every(i => i.complete)", 20)
    time.sleep(0.3)
    assert b.js("document.title") == f"Wand calibration rig.toml: {report['grade']}"
    assert b.js("document.getElementById('grade').innerText") == report["grade"]
    assert b.js("document.getElementById('grade-reason').innerText") == \
        report["grade_reason"]
    assert "What to do" in b.js("document.getElementById('advice').innerText")
    # every image decoded to a picture of some size
    sizes = b.js("[...document.images].map(i => [i.id, i.naturalWidth, i.naturalHeight])")
    assert sorted(s[0] for s in sizes) == ["coverage", "layout", "residuals"]
    assert all(w > 100 and h > 100 for _, w, h in sizes), sizes
    # the tables carry the JSON's figures, cell for cell
    cams = b.js("""[...document.querySelectorAll('#cameras tr')].slice(1).map(r =>
        [...r.cells].map(c => c.dataset.value === undefined ? c.innerText
                                                               : Number(c.dataset.value)))""")
    assert [r[0] for r in cams] == [c["name"] for c in report["cameras"]]
    for row, c in zip(cams, report["cameras"], strict=True):
        assert row[1] == c["observations"]
        assert row[2] == pytest.approx(100 * c["coverage"], rel=1e-12)
        assert row[3] == pytest.approx(c["reprojection_rms_px"], rel=1e-12)
        assert row[4] == pytest.approx(c["held_out_rms_px"], rel=1e-12)
    figs = b.js("""Object.fromEntries([...document.querySelectorAll('#figures tr')]
        .slice(1).map(r => [r.cells[0].innerText,
                            [Number(r.cells[1].dataset.value),
                             Number(r.cells[2].dataset.value)]]))""")
    for label, key in (("reprojection RMS (px)", "reprojection_rms_px"),
                       ("wand length error, SD (mm)", "wand_length_error_sd_mm"),
                       ("frames", "frames")):
        assert figs[label] == pytest.approx([report["solve"][key],
                                             report["held_out"][key]], rel=1e-12)
    shown = b.js("document.querySelector('#figures tr:nth-child(2) td:nth-child(2)')"
                 ".innerText")
    assert shown == f"{report['solve']['reprojection_rms_px']:.3f}"
    # the rig drawn: a frustum per camera in each view, at the camera's place
    assert b.js("document.querySelectorAll('#rig-top .frustum').length") == \
        len(report["cameras"])
    boxes = b.js("""[...document.querySelectorAll('#rig-top .frustum path')].map(p => {
        const r = p.getBBox(); return [r.x, r.y, r.width, r.height]; })""")
    assert all(w > 3 and h > 3 for _, _, w, h in boxes)
    centres = np.array([c["centre_m"] for c in report["cameras"]])
    order_x = np.argsort([x + w / 2 for x, _, w, _ in boxes])
    assert order_x.tolist() == np.argsort(centres[:, 0]).tolist()
    # nothing was fetched, nothing failed
    failed = [e for e in b.events if e["method"] == "Network.loadingFailed"]
    requested = [e["params"]["request"]["url"][:40] for e in b.events
                 if e["method"] == "Network.requestWillBeSent"
                 and not e["params"]["request"]["url"].startswith(("data:", "file:"))]
    assert failed == [] and requested == []


def test_report_to_a_missing_folder_is_one_line(calibkit_cli, tmp_path):
    r = calibkit_cli("wand", "--sim", "--out", tmp_path / "o.toml", "--report",
                     tmp_path / "nope" / "r.html")
    assert r.code == 2 and "--report" in r.err and len(r.err.strip().splitlines()) == 1


@needs_browser
def test_intrinsic_report_renders_with_the_json_figures(browser, calibkit_cli, tmp_path):
    """`calibkit intrinsic --sim --report`: a section per camera, its figures those of
    --json, its dots drawn per view, the distortion plots decoded, nothing fetched."""
    r = calibkit_cli("intrinsic", "--sim", "--cameras", 3, "--camera", "all", "--no-render",
                     "--views", 4, "--step", 120, "--seed", 2, "--rig", tmp_path / "i.toml",
                     "--json", tmp_path / "i.json", "--report", tmp_path / "i.html")
    assert r.code == 0, r.err
    figs = json.loads((tmp_path / "i.json").read_text())["cameras"]
    b = browser
    _show(b, tmp_path / "i.html")
    assert b.wait_for("document.readyState === 'complete' && document.images.length === 3"
                      " && [...document.images].every(i => i.complete)", 20)
    assert b.js("document.title") == "Intrinsic calibration cam0, cam1, cam2"
    sizes = b.js("[...document.images].map(i => [i.naturalWidth, i.naturalHeight])")
    assert all(w > 100 and h > 100 for w, h in sizes), sizes
    for k, f in enumerate(figs):
        values = b.js(f"""Object.fromEntries([...document.querySelectorAll(
            '#intrinsics-{k} tr')].slice(1).map(r => [r.cells[0].innerText,
            [Number(r.cells[1].dataset.value), Number(r.cells[2].dataset.value)]]))""")
        assert values["fx (px)"] == pytest.approx([f["fx"], f["std"]["fx"]], rel=1e-12)
        assert values["cy (px)"] == pytest.approx([f["cy"], f["std"]["cy"]], rel=1e-12)
        assert values["k1"][0] == pytest.approx(f["dist"][0], rel=1e-12)
        dots = b.js(f"""[...document.querySelectorAll('#dots-{k} .view')]
            .map(g => Number(g.dataset.dots))""")
        assert len(dots) == f["views"] and sum(dots) == f["points"]
        rms = b.js(f"Number(document.querySelector('#summary-{k} td').dataset.value)")
        assert rms == pytest.approx(f["rms_px"], rel=1e-12)
    assert [e for e in b.events if e["method"] == "Network.loadingFailed"] == []
    assert [e for e in b.events if e["method"] == "Network.requestWillBeSent"
            and not e["params"]["request"]["url"].startswith(("data:", "file:"))] == []


@needs_browser
def test_extrinsic_report_renders_with_the_json_figures(browser, calibkit_cli, tmp_path):
    r = calibkit_cli("intrinsic", "--sim", "--cameras", 3, "--camera", "all", "--no-render",
                     "--views", 4, "--step", 120, "--seed", 4, "--rig", tmp_path / "i.toml")
    assert r.code == 0, r.err
    r = calibkit_cli("extrinsic", "--projector", "--sim", "--intrinsics", tmp_path / "i.toml",
                     "--seed", 4, "--out", tmp_path / "ex.toml", "--json",
                     tmp_path / "ex.json")
    assert r.code == 0, r.err
    report = json.loads((tmp_path / "ex.json").read_text())
    b = browser
    _show(b, tmp_path / "ex.report.html")
    assert b.wait_for("document.readyState === 'complete'", 20)
    n = len(report["calibrated"])
    assert b.js("document.title") == \
        f"Extrinsic calibration ex.toml: {n} of {len(report['cameras'])} cameras placed"
    rows = b.js("""[...document.querySelectorAll('#cameras tr')].slice(1).map(r =>
        [r.cells[0].innerText, Number(r.cells[4].dataset.value),
         Number(r.cells[5].dataset.value)])""")
    assert [x[0] for x in rows] == [c["name"] for c in report["cameras"]]
    for row, c in zip(rows, report["cameras"], strict=True):
        assert row[1:] == pytest.approx([c["reprojection_rms_px"],
                                         c["mean_ray_distance_mm"]], rel=1e-12)
    assert b.js("document.querySelectorAll('#rig-top .frustum').length") == n
    assert b.js("document.querySelectorAll('#rig-top .points circle').length") > 100
    assert "calibkit wand --rig ex.toml --dots ex.dots.npz" in b.text()
    assert [e for e in b.events if e["method"] == "Network.loadingFailed"] == []
    assert [e for e in b.events if e["method"] == "Network.requestWillBeSent"
            and not e["params"]["request"]["url"].startswith(("data:", "file:"))] == []
