#!/usr/bin/env python3
"""The example plots the docs show (``docs/images/``), made by the commands a user runs: a run's track and errors
(``warptan run S8``, the demonstration), the information map (``warptan terrain info rugged --information --sensor
S8``) and a campaign's plot (S8, 60 s, 4 seeds, particles × likelihood). Each is written by warptan itself into a
scratch folder, then copied into ``docs/images/`` at a width the pages show (at most 760 px).

    python scripts/docs_images.py            # CPU: about a minute
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CAMPAIGN = """# the docs' example campaign (scripts/docs_images.py)
scenarios = ["S8"]
seeds = 4
[overrides]
duration_s = 60.0
[sweep]
particles = [250, 1000]
likelihood = ["paper", "gaussian"]
"""


def shrink(src: Path, dst: Path, width: int = 760) -> None:
    """``src`` at most ``width`` pixels wide into ``dst`` (Pillow, which matplotlib brings)."""
    from PIL import Image

    with Image.open(src) as img:
        if img.width > width:
            img = img.resize((width, round(img.height * width / img.width)), Image.LANCZOS)
        img.convert("RGB").save(dst, optimize=True)  # (full colour: a 256-colour palette drew thin red lines purple)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "images"))
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        warptan = [sys.executable, "-m", "warptan"]
        subprocess.run([*warptan, "run", "S8", "--device", "cpu", "--out", str(work / "run"), "--quiet"], check=True,
                       stdout=subprocess.DEVNULL)
        subprocess.run([*warptan, "terrain", "info", "rugged", "--information", "--sensor", "S8", "--out",
                        str(work / "information.png")], check=True, stdout=subprocess.DEVNULL)
        (work / "campaign.toml").write_text(CAMPAIGN)
        subprocess.run([*warptan, "campaign", str(work / "campaign.toml"), "--device", "cpu", "--out",
                        str(work / "campaign"), "--quiet"], check=True, stdout=subprocess.DEVNULL)
        made = {"run_track.png": work / "run" / "S8_seed0_track.png",
                "run_errors.png": work / "run" / "S8_seed0_errors.png",
                "information_S8.png": work / "information.png",
                "campaign_particles.png": work / "campaign" / "campaign_particles.png"}
        for name, src in made.items():
            shrink(src, out / name)
            print(f"wrote {out / name}")
        shutil.rmtree(work / "run")
    return 0


if __name__ == "__main__":
    sys.exit(main())
