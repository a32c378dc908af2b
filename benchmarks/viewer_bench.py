"""How large and how fluid the viewer page is: plan DESI 5000 (or read a run), write the page,
and time drawing frames in headless Chromium (Debian's /usr/bin/chromium, Playwright)::

    python benchmarks/viewer_bench.py --out benchmarks/results/viewer.json [--run RUN.h5]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_info

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]


def main() -> None:
    from playwright.sync_api import sync_playwright

    import fiberplan as fp
    from fiberplan.viewer import frame_indices, write_viewer

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--run", type=Path, default=None, help="A trajectory file (default: plan DESI 5000 random seed 0 with the mpc).")
    args = parser.parse_args()
    result = fp.load_result(args.run) if args.run else fp.plan(fp.make_scenario("desi", 5000, "random", 0), "mpc")
    report = fp.verify(result.scenario, result.trajectory)
    with tempfile.TemporaryDirectory() as scratch:
        page_path = write_viewer(result, report, Path(scratch) / "run.html")
        size_mb = page_path.stat().st_size / 1e6
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            page.goto(page_path.as_uri())
            page.wait_for_function("window.viewer && window.viewer.drawn > 0", timeout=60_000)
            ms = page.evaluate("(() => {const t0 = performance.now(); for (let f = 0; f < 60; f++) window.viewer.frame = f;"
                               " return (performance.now() - t0) / 60;})()")
            browser.close()
    frames = len(frame_indices(len(result.trajectory.times), result.scenario.n_positioners))
    out = {"benchmark": "viewer", "date_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "machine": machine_info(("playwright",)),
           "positioners": result.scenario.n_positioners, "samples": len(result.trajectory.times), "frames": frames,
           "page_mb": round(size_mb, 2), "draw_ms_per_frame": round(ms, 2),
           "browser": "Debian chromium, headless, software rendering (--disable-gpu)"}
    args.out.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "machine"}))


if __name__ == "__main__":
    main()
