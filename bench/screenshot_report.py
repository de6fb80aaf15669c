"""The screenshot of a case report in docs/ (``make docs/report.png``): the page as headless
Chromium shows it, its top ``--max-height`` pixels.

    python bench/screenshot_report.py out/demo/review/report.html --out docs/report.png

It also says what a reader of the report relies on, as the browser saw it: every picture
loaded, and no request left the file (the test, tests/reconstructor/test_report.py, checks the
same on a tiny case)."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.browser import CHROMIUM_MISSING, SKIP_REASON, HeadlessChromium


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("report", type=Path, help="an egosurg report HTML file")
    p.add_argument("--out", type=Path, default=Path("docs/report.png"))
    p.add_argument("--width", type=int, default=1150, help="the page's width, px (1150)")
    p.add_argument("--max-height", type=int, default=2400, help="keep the top this many px")
    args = p.parse_args()
    if CHROMIUM_MISSING:
        print(SKIP_REASON, file=sys.stderr)
        return 2
    if not args.report.is_file():
        print(f"{args.report} does not exist: make it with 'egosurg report' (or 'make demo')",
              file=sys.stderr)  # fmt: skip
        return 2
    with tempfile.TemporaryDirectory() as profile:
        browser = HeadlessChromium(Path(profile), (args.width, 900))
        try:
            browser.call("Network.enable")
            browser.call("Page.enable")
            browser.call("Page.navigate", url=args.report.resolve().as_uri())
            browser.wait_for("Page.loadEventFired", timeout_s=120)
            images = browser.evaluate(
                "Array.from(document.images).map(i => i.complete && i.naturalWidth > 0)"
            )
            shot = browser.screenshot(full_page=True)
            requests = [e["params"]["request"]["url"] for e in browser.events
                        if e["method"] == "Network.requestWillBeSent"]  # fmt: skip
        finally:
            browser.close()
    outside = [u for u in requests if not u.startswith(("data:", "file:"))]
    print(f"{sum(images)} of {len(images)} pictures loaded; requests outside the file: "
          f"{len(outside)}; page {shot.shape[1]}x{shot.shape[0]} px")  # fmt: skip
    top = np.ascontiguousarray(shot[: args.max_height, :, ::-1])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), top, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {args.out} ({top.shape[1]}x{top.shape[0]} px)")
    return 0 if all(images) and not outside else 1


if __name__ == "__main__":
    sys.exit(main())
