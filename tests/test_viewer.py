"""The interactive viewer: one self-contained HTML file, loaded, played and screenshotted in a
real headless Chromium (Debian's /usr/bin/chromium, driven by Playwright).

Without Chromium the browser test is skipped, unless FIBERPLAN_REQUIRE_BROWSER=1 (set by .ci/run,
which installs it), when it fails."""

from __future__ import annotations

import os
import re
import shutil

import pytest

import fiberplan as fp
from fiberplan.cli import main
from fiberplan.viewer import MAX_SAMPLES, frame_indices, page_data

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]


def _browser_or_skip():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sync_playwright = None
    if CHROMIUM is None or sync_playwright is None:
        if os.environ.get("FIBERPLAN_REQUIRE_BROWSER") == "1":
            pytest.fail("the viewer test needs Chromium and Playwright (.ci/run installs them)")
        pytest.skip("no Chromium or Playwright here")
    return sync_playwright


@pytest.fixture(scope="module")
def desi_run_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("view") / "r.h5"
    fp.save_result(fp.plan(fp.make_scenario("desi", 500, "random", 1), "mpc"), path)
    return path


def test_frames_are_decimated_within_the_budget():
    frames = frame_indices(232, 5000)
    assert frames[0] == 0 and frames[-1] == 231 and len(frames) * 5000 <= MAX_SAMPLES
    assert len(frame_indices(50, 61)) == 50


def test_page_data_marks_collisions_and_reasons():
    scenario = fp.make_scenario("desi", 19, "random", 3)
    result = fp.plan(scenario, "straight")
    report = fp.verify(scenario, result.trajectory)
    data = page_data(result, report)
    assert len(data["ids"]) == 19 and data["verified"] is report.ok
    named = {int(k) for k in data["colliding"]}
    assert named == {c.id_i for c in report.collisions} | {c.id_j for c in report.collisions}


def test_view_in_a_real_browser(desi_run_file, tmp_path, capsys):
    sync_playwright = _browser_or_skip()
    out = tmp_path / "run.html"
    main(["view", str(desi_run_file), "--out", str(out)])
    assert "wrote" in capsys.readouterr().out
    html = out.read_text()
    assert not re.search(r"""<(script|link)[^>]+(src|href)=["']?https?:""", html), "the page must not load anything from the network"
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(out.as_uri())
        page.wait_for_function("window.viewer && window.viewer.drawn > 0")
        before = page.screenshot()
        page.fill("#slider", "0")
        page.dispatch_event("#slider", "input")
        start = page.screenshot()
        page.fill("#slider", "120")
        page.dispatch_event("#slider", "input")
        assert page.evaluate("window.viewer.frame") == 120
        assert page.screenshot() != start, "moving the slider must move the arms"
        page.click("#play")
        page.wait_for_function("window.viewer.frame > 125", timeout=10_000)
        page.click("#play")
        page.fill("#search", "17")
        page.click("#find")
        assert page.evaluate("window.viewer.selected()") == 17
        assert "outcome: reached" in page.inner_text("#info")
        page.screenshot(path=str(tmp_path / "viewer.png"))
        browser.close()
    assert before and (tmp_path / "viewer.png").stat().st_size > 10_000
    assert errors == []


def test_view_refuses_a_non_html_output(desi_run_file, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["view", str(desi_run_file), "--out", str(tmp_path / "run.png")])
    assert exc.value.code == 2
