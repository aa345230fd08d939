"""Regenerate the screenshots in ``docs/screenshots/``: runs the browser tests that save them
(headless Debian Chromium) as they drive the consent page, the tutorial, each domain's teaching
page, the MTurk replica, the completion page and the dashboard.

    python scripts/screenshots.py [extra pytest arguments]
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "screenshots"
# The test modules that save the screenshots the README and the docs show.
MODULES = ("tests/browser/test_page.py", "tests/browser/test_mturk_run.py")


def main(argv: list[str]) -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    environment = {**os.environ, "BAM_SCREENSHOT_DIR": str(OUT)}
    command = [sys.executable, "-m", "pytest", "-m", "browser", *MODULES, *argv]
    result = subprocess.run(command, cwd=ROOT, env=environment, check=False)
    if result.returncode == 0:
        for path in sorted(OUT.glob("*.png")):
            print(f"{path.relative_to(ROOT)}  {path.stat().st_size // 1024} KiB")
    return result.returncode


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
