"""Render every bundled preset to docs/gallery/NAME.png (the README gallery).

    python tools/gallery.py [--width 320 --height 180]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torchvol as tv
from torchvol.cli import write_png

OUT = Path(__file__).resolve().parents[1] / "docs" / "gallery"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=180)
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    for name in tv.preset_names():
        start = time.perf_counter()
        out = tv.render(tv.preset(name, width=args.width, height=args.height))
        write_png(OUT / f"{name}.png", out.image[0].permute(1, 2, 0).numpy())
        print(f"{name}: {time.perf_counter() - start:.2f} s, passes {out.stats['passes']}", flush=True)


if __name__ == "__main__":
    main()
