"""Screenshot of a Rerun recording as the web viewer shows it (the docs' pictures).

    python scripts/viewer_screenshot.py RECORDING.rrd OUT.png [--wait-s 40] [--size 1800x1100]

Serves the recording with the ``rerun`` tool that ships in rerun-sdk (gRPC + web viewer on
loopback), opens it in headless Chromium (Debian package ``chromium``; software WebGL through
SwiftShader), waits for the viewer to load and lay out the recording's blueprint, and writes a
PNG. Needs the ``docs`` extra (playwright, used only to drive the browser; no browser download).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

from lab.launcher import LaunchError, free_port, wait_listening
from smartedge.viewer.rerun_view import rerun_cli

CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--wait-s", type=float, default=40.0,
                        help="time for the viewer to load (software rendering is slow)")
    parser.add_argument("--size", default="1800x1100", help="window size WxH")
    parser.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    args = parser.parse_args(argv)
    if not args.recording.is_file():
        print(f"viewer_screenshot: no recording at {args.recording}", file=sys.stderr)
        return 2
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        print("viewer_screenshot: needs playwright (pip install -e '.[docs]')", file=sys.stderr)
        return 2
    width, height = (int(v) for v in args.size.split("x"))
    web_port, grpc_port = free_port(), free_port()
    server = subprocess.Popen(
        [str(rerun_cli()), "--serve-web", "--web-viewer-port", str(web_port), "--port",
         str(grpc_port), "--renderer", "webgl", str(args.recording)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        try:
            wait_listening(web_port, timeout_s=30, step_s=0.2)
        except LaunchError:
            raise SystemExit(f"the rerun web viewer did not come up on port {web_port}") from None
        url = (f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}"
               "%2Fproxy&renderer=webgl")
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=args.chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            page.wait_for_timeout(args.wait_s * 1000)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(args.out))
            browser.close()
    finally:
        server.terminate()
        server.wait(10)
    print(f"viewer_screenshot: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
