"""`torchvol render | generate | sweep | bench`: thin shell over the library; errors print as one line, exit code 2."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from .keypath import parse_value
from .scene import load_scene, preset
from .validate import SceneError, fail


def _pairs(items: Sequence[str], flag: str) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            fail(flag, item, "expected KEY=VALUE")
        out[key.strip()] = parse_value(value.strip())
    return out


def write_png(path: Path, image: np.ndarray) -> None:
    """`image`: (H, W, 3) or (H, W) float in [0, 1] -> 8-bit PNG."""
    from PIL import Image

    Image.fromarray(np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)).save(path)


def write_depth_png(path: Path, depth: np.ndarray) -> None:
    """16-bit PNG for viewing: value = depth / depth_scale · 65535, depth_scale stored as PNG text.
    Exact float32 depth is written with --npy."""
    from PIL import Image, PngImagePlugin

    scale = float(depth.max()) if depth.max() > 0 else 1.0
    info = PngImagePlugin.PngInfo()
    info.add_text("depth_scale", repr(scale))
    info.add_text("depth", "planar z along the camera's forward axis, world units; 0 = nothing hit")
    Image.fromarray(np.round(depth / scale * 65535).astype(np.uint16)).save(path, pnginfo=info)


def cmd_render(args: argparse.Namespace) -> int:
    from .render import render

    overrides = _pairs(args.set, "--set")
    if args.preset is not None:
        if args.scene is not None:
            fail("SCENE", args.scene, "give a scene file or --preset, not both")
        scene = load_scene(preset(args.preset, **_pairs(args.param, "--param")), overrides)
    elif args.scene is not None:
        if args.param:
            fail("--param", args.param, "--param sets preset parameters; use --set for scene keys")
        scene = load_scene(args.scene, overrides)
    else:
        fail("SCENE", None, "give a scene (.toml path or preset name) or --preset NAME")
    out = render(scene, seed=args.seed, chunk_rays=args.chunk_rays, compile=args.compile, device=args.device)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    stem = path.with_suffix("")
    write_png(path, out.image[0].permute(1, 2, 0).numpy())
    write_depth_png(Path(f"{stem}_depth.png"), out.depth[0, 0].numpy())
    written = [str(path), f"{stem}_depth.png"]
    if args.npy:
        arrays = {"radiance": out.radiance, "depth": out.depth, "alpha": out.alpha, **out.aovs}
        for name, value in arrays.items():
            np.save(f"{stem}_{name}.npy", value[0].numpy())
            written.append(f"{stem}_{name}.npy")
        np.save(f"{stem}_K.npy", out.camera.K[0].cpu().numpy())
        np.save(f"{stem}_world_to_camera.npy", out.camera.world_to_camera[0].cpu().numpy())
        written += [f"{stem}_K.npy", f"{stem}_world_to_camera.npy"]
    stats = {k: out.stats[k] for k in ("passes", "density_evals", "total_s", "march_steps")}
    print(json.dumps({"written": written, **stats}))
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from .generate import generate

    report = generate(args.recipe, count=args.count, out=args.out, seed=args.seed, workers=args.workers,
                      layout=args.format, overrides=_pairs(args.set, "--set"), batch=args.batch,
                      shard_size=args.shard_size, threads=args.threads, scheduler=args.scheduler)
    print(json.dumps(report))
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from .sweep import split_values, sweep

    params = {}
    for item in args.param:
        key, sep, values = item.partition("=")
        if not sep or not key.strip() or not values.strip():
            fail("--param", item, "expected KEY=V1,V2,...")
        params[key.strip()] = [parse_value(v) for v in split_values(values)]
    if not params:
        fail("--param", None, "give at least one --param KEY=V1,V2,...")
    rows = sweep(args.scene, params, out=args.out, seed=args.seed, overrides=_pairs(args.set, "--set"))
    print(json.dumps({"out": args.out, "combinations": len(rows)}))
    return 0


def cmd_bench_accuracy(args: argparse.Namespace) -> int:
    from .bench import accuracy

    def names(text: str | None) -> list[str] | None:
        return None if text is None else [v.strip() for v in text.split(",") if v.strip()]

    rows = accuracy(args.out, width=args.width, height=args.height, repeat=args.repeat,
                    scenes=names(args.scenes), knob_names=names(args.knobs), seed=args.seed)
    print(json.dumps({"written": [str(Path(args.out) / "accuracy.md"), str(Path(args.out) / "accuracy.png")],
                      "rows": len(rows)}))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchvol", description="Batched PyTorch renderer of volumes and voxels.")
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render one scene to PNG (+ depth, + float arrays with --npy)")
    r.add_argument("scene", nargs="?", help="scene .toml path or preset name")
    r.add_argument("--preset", help="bundled preset name (its parameters via --param)")
    r.add_argument("--param", action="append", default=[], metavar="K=V", help="preset parameter")
    r.add_argument("--set", action="append", default=[], metavar="A.B=V", help="override a scene key")
    r.add_argument("--out", required=True, help="output PNG path")
    r.add_argument("--npy", action="store_true", help="also write float32 .npy arrays and the camera")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--device", default="cpu")
    r.add_argument("--chunk-rays", type=int, default=1 << 16)
    r.add_argument("--compile", action="store_true", help="torch.compile the density fields")
    r.set_defaults(func=cmd_render)

    g = sub.add_parser("generate", help="render recipe samples into a dataset folder or webdataset shards (resumable)")
    g.add_argument("recipe", help="recipe .toml path (see datasets/)")
    g.add_argument("--count", type=int, required=True, help="number of samples")
    g.add_argument("--out", required=True, help="output folder (a re-run finishes an interrupted one)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--workers", type=int, default=1, help="local worker processes")
    g.add_argument("--threads", type=int, default=None, help="torch threads per worker (default: cores / workers)")
    g.add_argument("--format", choices=["folder", "webdataset"], default="folder")
    g.add_argument("--set", action="append", default=[], metavar="A.B=V", help="override a recipe key")
    g.add_argument("--batch", type=int, default=4, help="samples rendered as one batch")
    g.add_argument("--shard-size", type=int, default=64, help="samples per webdataset shard")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS", help="run the tasks on this Dask cluster")
    g.set_defaults(func=cmd_generate)

    w = sub.add_parser("sweep", help="render every combination of swept values; results.csv, contact sheet, plots")
    w.add_argument("scene", help="scene .toml path or preset name")
    w.add_argument("--param", action="append", default=[], metavar="A.B=V1,V2,...", help="a swept key and its values")
    w.add_argument("--set", action="append", default=[], metavar="A.B=V", help="override a scene key")
    w.add_argument("--out", required=True, help="output folder")
    w.add_argument("--seed", type=int, default=0)
    w.set_defaults(func=cmd_sweep)

    b = sub.add_parser("bench", help="benchmarks").add_subparsers(dest="bench", required=True)
    a = b.add_parser("accuracy", help="error against time per knob and quality level: DIR/accuracy.md, DIR/accuracy.png")
    a.add_argument("--out", required=True, help="output folder")
    a.add_argument("--width", type=int, default=64)
    a.add_argument("--height", type=int, default=36)
    a.add_argument("--repeat", type=int, default=3, help="renders per point; time is their median")
    a.add_argument("--scenes", default=None, help="comma-separated presets (default: template-clouds, cloud-puff, voxel-terrain)")
    a.add_argument("--knobs", default=None, help="comma-separated subset of steps, integrator, shadow_steps, lod, spp, compile, tolerance")
    a.add_argument("--seed", type=int, default=0)
    a.set_defaults(func=cmd_bench_accuracy)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except SceneError as err:
        print(f"torchvol: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
