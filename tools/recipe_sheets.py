"""Render 16 samples of each recipe into a contact sheet, docs/images/sheet-NAME.png (datasets/README.md).

    python tools/recipe_sheets.py [NAME ...] [--count 16 --width 128 --height 96]

Samples are index 0..count−1 at seed 0, rendered as the generator renders them (`SceneDataset.batch`),
each labelled with its index; a multi-view recipe (`[dataset] views = V`) shows count/V samples, a
row of its V views each.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torchvol as tv
from torchvol.measure.figures import contact_sheet

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="recipe names (datasets/NAME.toml); all when none")
    parser.add_argument("--count", type=int, default=16)
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=96)
    args = parser.parse_args()
    names = args.names or sorted(p.stem for p in (ROOT / "datasets").glob("*.toml"))
    for name in names:
        start = time.perf_counter()
        recipe = tv.Recipe.load(ROOT / "datasets" / f"{name}.toml")
        if recipe.sequence is not None:  # a sequence's sheet shows each sample's frame 0 (tools/sequence_strip.py: all)
            recipe = tv.Recipe.load(recipe, {"dataset.frames": 1})
        count = max(1, args.count // recipe.views)  # a multi-view recipe: a row per sample, a tile per view
        ds = tv.SceneDataset(recipe, count, aovs=(), overrides={"image.width": args.width, "image.height": args.height})
        samples = [s for first in range(0, count, 4) for s in ds.batch(range(first, min(count, first + 4)))]
        # a mixed recipe's tiles also name the family each sample drew
        tiles = [([f"{name} #{s['index']}" + (f" view {v}" if recipe.views > 1 else "")
                   + (f" {s['params']['family']}" if "family" in s["params"] else "")], image)
                 for s in samples for v, image in enumerate(s["image"] if recipe.views > 1 else [s["image"]])]
        contact_sheet(tiles, ROOT / "docs" / "images" / f"sheet-{name}.png", columns=4)
        print(f"{name}: {time.perf_counter() - start:.1f} s", flush=True)


if __name__ == "__main__":
    main()
