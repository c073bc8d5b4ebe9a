"""The web viewer draws a run: ``threedq view --serve`` on a run folder, a headless Chromium (software WebGL) opens
the printed address, and the page is screenshotted through the DevTools protocol until the scenes' 3D view is drawn
(many distinct colours) or the time is up. Needs Chromium and ``websocket-client``; not part of the test suite.

    python scripts/view_browser_check.py [--run runs/em] [--out docs/img/viewer.png] [--max_scenes 16]
"""

from __future__ import annotations

import argparse
import base64
import itertools
import json
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np


def drawn_colours(png: bytes) -> int:
    """Distinct colours (8 levels a channel) in the left half's middle of the page: where the scenes' view is."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    h, w = img.shape[:2]
    return len(np.unique(img[h // 4 : 3 * h // 4, w // 8 : w // 2].reshape(-1, 3) // 8, axis=0))


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--run", default="runs/em")
    ap.add_argument("--out", default="docs/img/viewer.png")
    ap.add_argument("--max_scenes", type=int, default=16)
    ap.add_argument("--port", type=int, default=9090)
    ap.add_argument("--seconds", type=float, default=180.0, help="how long to wait for the page to draw")
    args = ap.parse_args()
    import websocket  # websocket-client: the DevTools protocol speaks over a websocket

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        print("view_browser_check: no chromium (apt-get install chromium)")
        return 2
    log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)  # noqa: SIM115 - the server writes it
    view = subprocess.Popen(["threedq", "view", "--run", args.run, "--serve", "true", "--port", str(args.port),
                             "--max_scenes", str(args.max_scenes), "--progress", "false"], stdout=log, stderr=log)
    browser = None
    try:
        url = None
        for _ in range(240):
            text = Path(log.name).read_text()
            if "web viewer at " in text:
                url = text.split("web viewer at ", 1)[1].split()[0]
                break
            if view.poll() is not None:
                print(text + "\nview_browser_check: threedq view stopped")
                return 1
            time.sleep(0.5)
        if url is None:
            print("view_browser_check: no address printed")
            return 1
        print(f"view_browser_check: {url}")
        profile = tempfile.mkdtemp()
        browser = subprocess.Popen([chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                                    "--enable-unsafe-swiftshader", "--window-size=1600,900",
                                    f"--user-data-dir={profile}", "--remote-debugging-port=9222", url],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        target = None
        for _ in range(60):
            try:
                pages = json.load(urllib.request.urlopen("http://127.0.0.1:9222/json", timeout=2))
                target = next(p for p in pages if p.get("type") == "page")
                break
            except (OSError, StopIteration):
                time.sleep(0.5)
        if target is None:
            print("view_browser_check: Chromium's DevTools did not answer")
            return 1
        ws = websocket.create_connection(target["webSocketDebuggerUrl"], timeout=30)
        ids = itertools.count(1)

        def screenshot() -> bytes:
            n = next(ids)
            ws.send(json.dumps({"id": n, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
            while (reply := json.loads(ws.recv())).get("id") != n:
                pass
            return base64.b64decode(reply["result"]["data"])

        t0, png = time.time(), b""
        while time.time() - t0 < args.seconds:
            time.sleep(5)
            colours = drawn_colours(png := screenshot())
            print(f"view_browser_check: after {time.time() - t0:.0f} s, {colours} colours in the scenes' view")
            if colours >= 200:
                time.sleep(5)  # let the labels and the time series settle, then keep that picture
                Path(args.out).parent.mkdir(parents=True, exist_ok=True)
                Path(args.out).write_bytes(screenshot())
                print(f"view_browser_check: drawn; wrote {args.out}")
                return 0
        Path(args.out).with_suffix(".failed.png").write_bytes(png)
        print(f"view_browser_check: the scenes' view is not drawn after {args.seconds:.0f} s "
              f"(last screenshot: {Path(args.out).with_suffix('.failed.png')})")
        return 1
    finally:
        for p in (browser, view):
            if p is not None:
                p.terminate()
                p.wait(timeout=30)


if __name__ == "__main__":
    sys.exit(main())
