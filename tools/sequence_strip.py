"""One sample of a sequence recipe as a strip: its frames, their depth and their colour-coded flow.

    python tools/sequence_strip.py [datasets/cloud-sequence.toml] [--index 1 --seed 0 --scale 2 --out PATH]

Rows: the F frames; depth (brighter = farther, black = no hit, scaled by the largest depth);
flow f -> f+1 coloured by direction (hue: angle of (dx, dy), 0 = +x, to the right; a quarter turn =
+y, down) and brightness by magnitude (the sample's largest = full), dark grey where flow_valid is 0
(sky; the last frame). Writes docs/images/sequence-NAME.png by default and prints the largest flow.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.colors import hsv_to_rgb
from PIL import Image

import torchvol as tv

ROOT = Path(__file__).resolve().parents[1]


def flow_colours(flow: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """flow (F, 2, H, W), valid (F, 1, H, W) -> (F, H, W, 3) in [0, 1]."""
    dx, dy = flow[:, 0], flow[:, 1]
    magnitude = np.hypot(dx, dy)
    hsv = np.stack([(np.arctan2(dy, dx) / (2 * np.pi)) % 1.0, np.ones_like(dx), magnitude / max(magnitude.max(), 1e-6)], -1)
    return np.where(valid[:, 0, ..., None] > 0, hsv_to_rgb(hsv), 0.15)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recipe", nargs="?", default=str(ROOT / "datasets" / "cloud-sequence.toml"))
    parser.add_argument("--index", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scale", type=int, default=2)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    item = tv.SceneDataset(args.recipe, args.index + 1, seed=args.seed)[args.index]
    if "flow" not in item:
        raise SystemExit(f"{args.recipe}: not a sequence recipe (no [dataset] frames > 1)")
    depth = item["depth"].numpy()
    rows = [item["image"].permute(0, 2, 3, 1).numpy(),
            np.repeat((depth / max(depth.max(), 1e-6)).transpose(0, 2, 3, 1), 3, -1),
            flow_colours(item["flow"].numpy(), item["flow_valid"].numpy())]
    sheet = np.concatenate([np.concatenate(list(r), 1) for r in rows], 0)
    picture = Image.fromarray((np.clip(sheet, 0, 1) * 255 + 0.5).astype(np.uint8))
    picture = picture.resize((picture.width * args.scale, picture.height * args.scale), Image.NEAREST)
    out = Path(args.out or ROOT / "docs" / "images" / f"sequence-{Path(args.recipe).stem}.png")
    picture.save(out)
    print(f"{out}: largest flow {np.abs(item['flow'].numpy()).max():.2f} px, valid {item['flow_valid'].mean():.2f}")


if __name__ == "__main__":
    main()
