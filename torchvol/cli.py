"""`torchvol render | generate | stats | sweep | bench`: thin shell over the library; errors print as one
line (exit code 2), progress goes to stderr."""

from __future__ import annotations

import argparse
import json
import os
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple, NoReturn, Sequence

import numpy as np

# no torch at module level: `main` tunes the process (`tune_process`) before anything imports torch
from .runtime.process import imports_uncollected, tune_process
from .schema.keypath import parse_value
from .schema.validate import SceneError, fail

# library parameters that a command line spells differently
FLAGS = {"layout": "--format", "overrides": "--set", "params": "--param", "knob_names": "--knobs", "source": "SOURCE"}


def _pairs(items: Sequence[str], flag: str) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            fail(flag, item, "expected KEY=VALUE")
        out[key.strip()] = parse_value(value.strip())
    return out


def presets_help() -> str:
    """Each bundled preset: what it is (its file's first comment line), its size and its parameters."""
    import tomllib

    from .scene.model import preset_names
    from .scene.presets import HERE, PARAMS

    lines = ["presets (--preset NAME, --param KEY=VALUE; every preset takes width and height):"]
    for name in preset_names():
        text = (HERE / f"{name}.toml").read_text()
        first = next((line[1:].strip() for line in text.splitlines() if line.startswith("#")), "")
        what = first.split(":")[0].split(" — ")[0].rstrip(".")
        image = tomllib.loads(text).get("image", {})
        params = ["width", "height"] + list((PARAMS[name].__kwdefaults__ or {}) if name in PARAMS else [])
        lines.append(f"  {name:<17} {what}; {image.get('width')}x{image.get('height')}; parameters: {', '.join(params)}")
    return "\n".join(lines)


def write_png(path: Path, image: np.ndarray) -> None:
    """`image`: (H, W, 3) or (H, W) float in [0, 1] -> 8-bit PNG."""
    from PIL import Image

    Image.fromarray(np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)).save(path)


def write_depth_png(path: Path, depth: np.ndarray) -> None:
    """16-bit PNG: value = round(depth / depth_scale · 65535), depth_scale (the largest depth) in
    the PNG's `depth_scale` text chunk; depth = value / 65535 · depth_scale, to within
    depth_scale / 131070 (README: reading it back). Exact float32 depth is written with --npy."""
    from PIL import Image, PngImagePlugin

    scale = float(depth.max()) if depth.max() > 0 else 1.0
    info = PngImagePlugin.PngInfo()
    info.add_text("depth_scale", repr(scale))
    info.add_text("depth", "planar z along the camera's forward axis, world units; 0 = nothing hit; "
                           "depth = value / 65535 * depth_scale")
    Image.fromarray(np.round(depth / scale * 65535).astype(np.uint16)).save(path, pnginfo=info)


def cmd_render(args: argparse.Namespace) -> int:
    """`torchvol render`: one scene to FILE.png, FILE_depth.png and with --npy its arrays;
    prints what it wrote as JSON. -> 0."""
    from .renderer.executor import render
    from .runtime.progress import progress
    from .scene.model import load_scene, preset

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
    with progress(scene.image.width * scene.image.height * scene.image.passes, desc="render", unit="px", enabled=args.progress) as bar:
        out = render(scene, seed=args.seed, chunk_rays=args.chunk_rays, compile=args.compile, device=args.device,
                     progress=bar.update)
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
    """`torchvol generate`: a recipe's samples into a dataset; prints the generator's report as
    JSON. -> 0."""
    from .dataset.generate import generate

    overrides = _pairs(args.set, "--set")
    report = generate(args.recipe, count=args.count, out=args.out, seed=args.seed, workers=args.workers,
                      layout=args.format, overrides=overrides, batch=args.batch,
                      shard_size=args.shard_size, threads=args.threads, scheduler=args.scheduler, progress=args.progress,
                      compile=args.compile)
    print(json.dumps(report))
    return 0


def cmd_stats(args: argparse.Namespace) -> int:
    """`torchvol stats`: a dataset's QA plot and tables; prints the table and warnings. -> 1
    when --strict and degenerate, else 0."""
    from .dataset.stats import write_stats

    stats = write_stats(args.dir, out=args.out, empty_alpha=args.empty_alpha, saturated_pixels=args.saturated_pixels,
                        max_share=args.max_share)
    print(open(stats["written"][2]).read(), end="")
    for line in stats["warnings"]:
        print(f"torchvol: warning: degenerate recipe: {line}", file=sys.stderr)
    print("wrote " + ", ".join(stats["written"]))
    return 1 if args.strict and stats["flagged"] else 0


def cmd_sweep(args: argparse.Namespace) -> int:
    """`torchvol sweep`: every combination of the swept values, measured; prints what it wrote
    and the verdict. -> 0."""
    from .measure.sweep import split_values, sweep

    params = {}
    for item in args.param:
        key, sep, values = item.partition("=")
        if not sep or not key.strip() or not values.strip():
            fail("--param", item, "expected KEY=V1,V2,...")
        params[key.strip()] = [parse_value(v) for v in split_values(values)]
    levels = [] if args.levels is None else [v.strip() for v in args.levels.split(",") if v.strip()]
    kw = {} if args.max_error is None else {"max_error": args.max_error}
    report = sweep(args.source, params, out=args.out, seed=args.seed, overrides=_pairs(args.set, "--set"),
                   samples=args.samples, levels=levels, factor=args.factor, cache=args.cache, progress=args.progress,
                   every_order=args.every_order, **kw)
    print("wrote " + ", ".join(report["written"]))
    print("verdict: " + report["verdict"])
    return 0


def cmd_bench_accuracy(args: argparse.Namespace) -> int:
    """`torchvol bench accuracy`: error against time per knob and level; prints what it wrote as
    JSON. -> 0."""
    from .measure.bench_accuracy import accuracy

    def names(text: str | None) -> list[str] | None:
        return None if text is None else [v.strip() for v in text.split(",") if v.strip()]

    rows = accuracy(args.out, width=args.width, height=args.height, repeat=args.repeat, scenes=names(args.scenes),
                    knob_names=names(args.knobs), seed=args.seed, factor=args.factor, cache=args.cache,
                    progress=args.progress)
    print(json.dumps({"written": [str(Path(args.out) / "accuracy.md"), str(Path(args.out) / "accuracy.png")],
                      "rows": len(rows)}))
    return 0


def cmd_bench_speed(args: argparse.Namespace) -> int:
    """`torchvol bench speed`: the speed report, printed (and written to --out). -> 0."""
    from .measure.bench_speed import speed

    print(speed(args.out, quick=args.quick, repeat=args.repeat, recipes=args.recipes, count=args.count, parts=args.parts,
                baseline=args.baseline))
    return 0


@dataclass(frozen=True)
class Command:
    """One command of the CLI as data: its `path` under `torchvol` (("bench", "speed")), the
    function it runs, its texts and its `options`: each `option(...)`, or a tuple of them (a
    mutually exclusive group). `raw`: keep the description's and epilog's lines as written
    (they are wrapped here); `progress`: add --no-progress."""

    path: tuple[str, ...]
    func: Callable[[argparse.Namespace], int]
    help: str
    options: tuple
    description: str | None = None
    epilog: str | Callable[[], str] | None = None  # a function: called when the help is printed
    raw: bool = False
    progress: bool = True


# commands that only group others: their help
GROUPS = {"bench": "benchmarks"}


class Option(NamedTuple):
    """One option of a `Command`: `add_argument`'s names and keywords."""

    names: tuple[str, ...]
    kwargs: dict


def option(*names: str, **kwargs) -> Option:
    """`Option(names, kwargs)`, written as the `add_argument` call it stands for."""
    return Option(names, kwargs)


def _wrap(text: str) -> str:
    return textwrap.fill(text, 100)


class HelpParser(argparse.ArgumentParser):
    """A parser whose epilog may be a function, called when the help is printed: the presets'
    list reads every preset's file (~25 ms of every command's start otherwise)."""

    def format_help(self) -> str:
        """argparse's help, the epilog made first where it is a function."""
        if callable(self.epilog):
            self.epilog = self.epilog()
        return super().format_help()


def build_parser() -> argparse.ArgumentParser:
    """The `torchvol` parser: every `Command` of `commands()` added as a subcommand."""
    parser = HelpParser(prog="torchvol", description="Batched PyTorch renderer of volumes and voxels.")
    subs = {(): parser.add_subparsers(dest="command", required=True)}
    for command in commands():
        *group, name = command.path
        if tuple(group) not in subs:
            subs[tuple(group)] = subs[()].add_parser(group[0], help=GROUPS[group[0]]).add_subparsers(dest=group[0], required=True)
        kw = {"formatter_class": argparse.RawDescriptionHelpFormatter} if command.raw else {}
        p = subs[tuple(group)].add_parser(name, help=command.help, description=command.description,
                                          epilog=command.epilog, **kw)
        for entry in command.options:
            if isinstance(entry, Option):
                p.add_argument(*entry.names, **entry.kwargs)
            else:  # a mutually exclusive group
                exclusive = p.add_mutually_exclusive_group()
                for names, kwargs in entry:
                    exclusive.add_argument(*names, **kwargs)
        if command.progress:
            p.add_argument("--no-progress", dest="progress", action="store_false",
                           help="no progress bar on stderr (by default a live bar on a terminal, a line every few seconds otherwise)")
        p.set_defaults(func=command.func)
    return parser


def commands() -> list[Command]:
    """Every command of the CLI, in the order `torchvol --help` lists them."""
    return [_render_command(), _generate_command(), _stats_command(), _sweep_command(), _accuracy_command(),
            _speed_command()]


def _render_command() -> Command:
    from .renderer.executor import DEFAULT_CHUNK_RAYS

    return Command(("render",), cmd_render, raw=True, epilog=presets_help,
                   help="render one scene to PNG (+ 16-bit depth PNG, + float arrays with --npy)",
                   description=_wrap("Render one scene: FILE.png (8-bit image), FILE_depth.png (16-bit: depth = "
                                     "value / 65535 * depth_scale, from the PNG's depth_scale text), and with --npy the "
                                     "exact float32 arrays and the camera."), options=(
        option("scene", nargs="?", help="scene .toml path or preset name"),
        option("--preset", help="bundled preset name (listed below; its parameters via --param)"),
        option("--param", action="append", default=[], metavar="K=V", help="a preset parameter (listed below), e.g. width=640"),
        option("--set", action="append", default=[], metavar="A.B=V", help="override a scene key (docs/SCENES.md), e.g. march.quality=high"),
        option("--out", required=True, help="output PNG path; FILE_depth.png and FILE_*.npy are written beside it"),
        option("--npy", action="store_true", help="also write float32 .npy arrays (radiance, depth, alpha, AOVs) and the camera (K, world_to_camera)"),
        option("--seed", type=int, default=0, help="render seed: march dither and sub-pixel jitter (default 0)"),
        option("--device", default="cpu", help="torch device to render on (default cpu)"),
        option("--chunk-rays", type=int, default=DEFAULT_CHUNK_RAYS,
               help=f"rays per chunk: bounds peak memory, not the result (default {DEFAULT_CHUNK_RAYS})"),
        option("--eager", dest="compile", action="store_const", const="off", default="kernels",
               help="render the eager reference: no Dr.Jit kernel (by default a technique that has one, a volume's "
               "march, the voxel walk, the terrain's tracing, runs in it, within ~1e-5 of eager)"),
    ))


def _generate_command() -> Command:
    return Command(("generate",), cmd_generate,
                   help="render recipe samples into a dataset folder or webdataset shards (resumable)",
                   description="Render COUNT samples of a recipe (datasets/*.toml) into OUT: atomic and resumable "
                               "(a re-run finishes an interrupted dataset byte-identically). docs/DATASETS.md.", options=(
        option("recipe", help="recipe .toml path (see datasets/), or a scene or preset name"),
        option("--count", type=int, required=True, help="number of samples"),
        option("--out", required=True, help="output folder (a re-run finishes an interrupted one)"),
        option("--seed", type=int, default=0, help="dataset seed: sample i depends only on (seed, i) (default 0)"),
        option("--workers", type=int, default=1, help="local worker processes (default 1)"),
        option("--threads", type=int, default=None, help="torch threads per worker (default 1: more workers scale better; docs/DATASETS.md, \"Threads on a shared machine\")"),
        option("--eager", dest="compile", action="store_const", const="off", default="kernels",
               help="render the eager reference: no Dr.Jit kernel (by default a technique that has one, a volume's "
               "march, the voxel walk, the terrain's tracing, runs in it, within ~1e-5 of eager), recorded in meta.json"),
        option("--format", choices=["folder", "webdataset"], default="folder", help="output layout (default folder)"),
        option("--set", action="append", default=[], metavar="A.B=V", help="override a recipe key (a value or a distribution)"),
        option("--batch", type=int, default=None, help="samples rendered as one batch (default: as many as fill "
               "65,536 rays, in at least two batches a worker)"),
        option("--shard-size", type=int, default=64, help="samples per webdataset shard (default 64)"),
        option("--scheduler", default=None, metavar="ADDRESS", help="run the tasks on this Dask cluster"),
    ))


def _stats_command() -> Command:
    from .dataset.stats import EMPTY_ALPHA, MAX_SHARE, SATURATED_PIXELS

    return Command(("stats",), cmd_stats, progress=False,
                   help="dataset QA: parameter and image-statistic distributions, degenerate-recipe flags",
                   description=_wrap("Read a generated dataset (folder or webdataset) and write DIR/stats.png "
                                     "(distributions of the drawn parameters and of mean radiance, alpha coverage, "
                                     "clipped share and depth), DIR/stats.json and DIR/stats.md; warn when more than "
                                     "--max-share of the images are empty or saturated (docs/DATASETS.md, QA)."), options=(
        option("dir", metavar="DIR", help="a folder written by `torchvol generate`"),
        option("--out", default=None, help="plot path (default DIR/stats.png)"),
        option("--empty-alpha", type=float, default=EMPTY_ALPHA,
               help=f"an image whose alpha coverage and hit share are both under this is empty (default {EMPTY_ALPHA})"),
        option("--saturated-pixels", type=float, default=SATURATED_PIXELS,
               help=f"an image with more than this share of pixels at 1.0 is saturated (default {SATURATED_PIXELS})"),
        option("--max-share", type=float, default=MAX_SHARE,
               help=f"a recipe with more than this share of empty or of saturated images is degenerate (default {MAX_SHARE})"),
        option("--strict", action="store_true", help="exit 1 when the recipe is degenerate"),
    ))


def _sweep_command() -> Command:
    from .measure.reference import EVERY_ORDER_MODES
    from .measure.sweep import QUANTISATION_RMSE
    from .scene.quality import QUALITY

    return Command(("sweep",), cmd_sweep, raw=True, epilog=presets_help,
                   help="time and error of every combination of swept values; results.csv, verdict, plots",
                   description=_wrap("Render every combination of the swept values and measure each against a "
                                     "reference whose own error bound is --factor times under it. SOURCE is a scene, a "
                                     "preset or a recipe (with --samples: the same N draws for every setting). Writes "
                                     "OUT/results.csv (row by row: a re-run resumes), summary.csv, pareto.png, "
                                     "contact_sheet.png, difference.png, plot_<key>.png, and prints a verdict."), options=(
        option("source", metavar="SOURCE", help="scene .toml path, preset name or recipe .toml path"),
        option("--param", action="append", default=[], metavar="A.B=V1,V2,...", help="a swept key and its values (repeatable)"),
        option("--set", action="append", default=[], metavar="A.B=V", help="override a scene (or recipe) key for every setting"),
        option("--out", required=True, help="output folder (a re-run of the same sweep resumes there)"),
        option("--samples", type=int, default=None, help="recipe samples per setting (required for a recipe)"),
        option("--levels", default=None, metavar="L1,L2",
               help=f"also measure these quality levels, each deciding every approximation ({', '.join(QUALITY)})"),
        option("--max-error", type=float, default=None,
               help=f"the RMSE the verdict's setting must stay within (default {QUANTISATION_RMSE:.2g}: 8-bit quantisation)"),
        option("--factor", type=float, default=10.0, help="how far under each error the reference's bound must be (default 10)"),
        option("--cache", default=None, help="folder of cached references (default OUT/references)"),
        option("--seed", type=int, default=0, help="render seed (a recipe: the dataset seed of its samples) (default 0)"),
        option("--every-order", default="auto", choices=EVERY_ORDER_MODES,
               help="also measure against a path-traced reference with every order of scattering: auto (scenes whose "
                    "volumes have multiple-scattering octaves), always (every scene [path] can trace), never"),
    ))


def _accuracy_command() -> Command:
    from .measure.bench_accuracy import KNOBS, SCENES, TECHNIQUES

    return Command(("bench", "accuracy"), cmd_bench_accuracy,
                   help="error against time per knob and quality level: DIR/accuracy.md, DIR/accuracy.png",
                   description="Error against time on the bundled scenes, per knob and per quality level, against the "
                               "same references as `torchvol sweep` (each with its own error bound). docs/QUALITY.md.", options=(
        option("--out", required=True, help="output folder (its references/ are reused by a re-run)"),
        option("--width", type=int, default=64, help="image width (default 64)"),
        option("--height", type=int, default=36, help="image height (default 36)"),
        option("--repeat", type=int, default=3, help="renders per point; time is their median (default 3)"),
        option("--scenes", default=None, help="comma-separated presets (default: " + ", ".join(SCENES.values())
               + "; also " + ", ".join(TECHNIQUES) + ", whose cost every report states)"),
        option("--knobs", default=None, help="comma-separated subset of " + ", ".join(KNOBS) + " (default all)"),
        option("--factor", type=float, default=10.0, help="how far under each error the reference's bound must be (default 10)"),
        option("--cache", default=None, help="folder of cached references (default OUT/references)"),
        option("--seed", type=int, default=0, help="render seed (default 0)"),
    ))


def _speed_command() -> Command:
    from .measure.bench_speed import BASELINE, PARTS

    return Command(("bench", "speed"), cmd_bench_speed, progress=False,
                   help="llvmpipe vs eager vs fast renders, the fbm floor, generation samples/s, loaded-machine "
                   "slowdown, the heap",
                   description="One run of every speed figure of docs/SPEED.md (torchvol.measure.bench_speed); ratios hold on any "
                               "machine, absolute times only on a quiet one.", options=(
        option("--out", default=None, help="write the Markdown report here (e.g. docs/SPEED.md)"),
        option("--quick", action="store_true", help="small sizes, two recipes (about 2 minutes on 2 cores)"),
        option("--repeat", type=int, default=None, help="runs per figure; the median is reported (default 3, quick 2)"),
        option("--recipes", nargs="+", default=None, metavar="NAME",
               help="bundled recipes whose generation is timed (default: every one; quick: clouds, template-clouds)"),
        option("--count", type=int, default=None, metavar="N",
               help="samples of a generation row's shorter run (default 16, quick 4; rows in kernels 4N)"),
        option("--parts", nargs="+", default=list(PARTS), choices=PARTS, metavar="PART",
               help="sections to run: " + ", ".join(PARTS) + " (default all)"),
        option("--baseline", default=BASELINE, metavar="REV",
               help="the commit whose default generation the baseline part times each recipe against, in a git "
                    f"worktree (default {BASELINE}: the commit issue 32 was filed on)"),
    ))


def _flag(path: str, args: argparse.Namespace) -> str:
    """A library parameter named in an error as the command line spells it (`count` -> `--count`)."""
    head, dot, rest = path.partition(".")
    if head in FLAGS:
        return FLAGS[head] + (" " + rest if rest else "")
    if head in vars(args) and not rest:
        return "--" + head.replace("_", "-")
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """The `torchvol` command: run `argv` (default: the process's arguments) -> the exit code; an
    input error prints one line and returns 2."""
    tune_process()  # torchvol's own process: before any command imports torch
    with imports_uncollected():  # every command renders (and `render`'s help lists the presets)
        from .renderer import executor  # noqa: F401  (torch with it)
        from .runtime.compilation import drjit_available

        drjit_available()  # Dr.Jit loaded once, here: the generator's forked workers inherit it
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except SceneError as err:
        print(f"torchvol: error: {_flag(err.path, args)}: got {err.value!r}; {err.allowed}", file=sys.stderr)
        return 2


def command() -> NoReturn:
    """The console script: `main`, then the process ends without Python's finalisation. Tearing
    down torch's modules took 0.6 s of a 3.5 s `generate` of 64 clouds (docs/SPEED.md); every file
    is closed and every worker joined when `main` returns, so only the standard streams need a flush.
    An exception takes the ordinary exit, traceback included."""
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    command()
