"""Which kernels a render runs compiled: the `compile` setting of `render`, `generate` and
`SceneDataset`. Two compilers serve them: Dr.Jit's LLVM backend builds the march kernels
(`volume.kernel_march`, `volume.drjit_march`) in about a second and caches them on disk;
torch.compile (inductor) builds the voxel walk and, opt-in, the density kernels.

* ``"auto"`` (the default): ``"kernels"``, and ``"exact"`` where a process renders at least
  `AUTO_COMPILE_SAMPLES` samples (`generate` decides from each worker's share of the samples
  still to render, `SceneDataset` from its length; never from what a process rendered before).
  Both give the same bytes, so a sample's bytes never depend on the dataset's size.
* ``"kernels"``: the Dr.Jit march kernels wherever the plan finds one for a volume's technique
  and Dr.Jit runs (float32 on the CPU, libLLVM present); the rest eager. Their output is the
  canonical one; it agrees with eager within the tolerances of tests/volume/test_kernel_march.py
  (~1e-5), not bitwise.
* ``"exact"``: also the kernels whose torch.compile output is bitwise the eager one — the voxel DDA
  walk with its fog and its hybrid jumps (`voxel.walk`): divisions, compares, integer steps and
  gathers, which inductor emits as eager computes them (its C++ is built with
  ``-ffp-contract=off`` and without unsafe math; the fog's exp stays eager). Where inductor cannot
  build them (`exact_kernel`), they run eagerly after one warning. On a GPU, Triton's code and
  atomic sums are not promised bitwise.
* ``"all"`` (``True``): also inductor's density and march kernels (`fastnoise`, `volume.fused`)
  where no Dr.Jit kernel serves, within ~1e-5 of eager: recorded in a generated dataset's meta.json.
* ``"off"`` (``False``, ``--eager``): every kernel eager: the reference, on any device and dtype.
"""

from __future__ import annotations

import contextlib
import functools
import sys
import warnings
from collections.abc import Callable
from typing import Literal

import numpy as np
import torch

from ..schema.validate import fail, is_integer

__all__ = ["AUTO_COMPILE_SAMPLES", "CompileMode", "auto_mode", "compile_mode", "compile_settings", "compiled", "drjit_available",
           "exact_kernel"]

CompileMode = Literal["off", "kernels", "exact", "all"]
MODES = ("off", "kernels", "exact", "all")
# samples a process renders before "auto" compiles: building the walk's kernels took 21-25 s in a
# fresh process with inductor's cache cold and 5-7 s warm, and saved 0.025 s (voxel-terrain) to
# 0.19 s (voxel-world) a 128² sample on one thread: from 512 a warm-cache run gains on every voxel recipe
AUTO_COMPILE_SAMPLES = 512


def compile_mode(value, *, path: str = "compile", auto: bool = False) -> str:
    """`value` (a mode name; a bool, numpy's too, or 0 / 1: true is "all", false "off"; None is
    "off") as a mode name; "auto" kept where `auto`, else resolved for one render ("kernels").
    Raises ValueError naming `path` otherwise."""
    if value is None:
        return "off"
    if isinstance(value, (bool, np.bool_)) or (is_integer(value) and value in (0, 1)):
        return "all" if value else "off"
    allowed = MODES + ("auto",)
    if not isinstance(value, str) or value not in allowed:
        fail(path, value, "expected " + ", ".join(allowed) + " (or True for all, False or None for off)")
    return value if auto or value != "auto" else "kernels"


# whether this process may use Dr.Jit: None until the first `drjit_available` probes it. A child
# forked after its parent started Dr.Jit (a DataLoader worker) uses it too: its kernels run there,
# the same bytes (tests/volume/test_kernel_march.py), since a sample's bytes must not depend on the workers
_USABLE: dict[str, bool | None] = {"usable": None}


def drjit_available(dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> bool:
    """Whether Dr.Jit's kernels can render in `dtype` on `device`: float32 on the CPU, `drjit`
    importable with its LLVM backend (it needs libLLVM), probed once a process. The plan asks
    (`renderer.plan`), once a render; nothing reads an environment variable per chunk."""
    if dtype != torch.float32 or torch.device(device).type != "cpu":
        return False
    if _USABLE["usable"] is None:
        _USABLE["usable"] = _probe()
    return bool(_USABLE["usable"])


def _probe() -> bool:
    try:
        import drjit as dr
    except ImportError:
        return False
    return bool(dr.has_backend(dr.JitBackend.LLVM))


def auto_mode(mode: str, samples: int) -> CompileMode:
    """A resolved mode: "auto" becomes "exact" for a process that will render `samples` ≥
    `AUTO_COMPILE_SAMPLES`, else "kernels" (`generate`: each worker's share; `SceneDataset`: its
    length): the same bytes either way."""
    if mode != "auto":
        return mode
    return "exact" if samples >= AUTO_COMPILE_SAMPLES else "kernels"


# inductor decides when it builds a CPU kernel whether its loops run on threads: serially where the
# first call's size (dynamic shapes: the size hint of every later call) or the thread count was
# small. Its on-disk cache then serves that serial kernel to every process, whatever the size: one
# 16×16 render left every later 2-thread template render on one thread (docs/VOLUMES.md, "Two
# threads"). With dynamic threads each kernel is one parallel region and OpenMP's thread count when
# it runs decides, and no graph is recompiled or cached per thread count.
INDUCTOR_OPTIONS = {"cpp.dynamic_threads": True}
VARIANTS = 64  # graphs a kernel may compile: a walk has up to 16 (limit × records or jumps × dtype)
# dynamo's "duck sizing" takes sizes equal on a first call for one size: a template's first light
# kernel call on 3 lit samples was built for exactly as many as a light direction's 3 coordinates
# and built again at the next call (124 s against 91.5 s for a first 128² render, inductor's cache
# cold). Read when a call is traced; set around the calls (`compile_settings`), never for the user's graphs
_SETTING = [False]  # inside `compile_settings`
# dynamo's settings from before the block's, once a kernel inside it has set them (`_set_for_block`):
# importing dynamo takes over a second, and a block around eager work never needs it
_BEFORE: list[tuple[int, bool]] = []


@contextlib.contextmanager
def compile_settings():
    """dynamo's settings for torchvol's kernels (`VARIANTS`, no duck sizing) inside the block,
    restored after it; nested blocks keep the outer one's. Set once around a render's chunk
    (`render`), not at each kernel call: a changed setting makes dynamo hash its whole config
    again at the next call: ~30-50 µs a call, 2-6% of a compiled template render. Where dynamo
    is not loaded yet, set at the block's first compiled call (`compiled`) instead: a block
    around eager work imports no dynamo."""
    if _SETTING[0]:
        yield
        return
    _SETTING[0] = True
    try:
        if "torch._dynamo" in sys.modules:
            _set_for_block()
        yield
    finally:
        _SETTING[0] = False
        if _BEFORE:
            import torch._dynamo.config as dynamo
            import torch.fx.experimental._config as shapes

            dynamo.recompile_limit, shapes.use_duck_shape = _BEFORE.pop()


def _set_for_block() -> None:
    """dynamo's settings for the enclosing `compile_settings` block, once per block."""
    if _BEFORE:
        return
    import torch._dynamo.config as dynamo
    import torch.fx.experimental._config as shapes

    _BEFORE.append((dynamo.recompile_limit, shapes.use_duck_shape))
    dynamo.recompile_limit, shapes.use_duck_shape = VARIANTS, False


@functools.cache
def compiled(fn: Callable) -> Callable:
    """`fn` under torch.compile: dynamic shapes (a march compacts its batch every step, one graph
    serves every size) and `INDUCTOR_OPTIONS`, in `compile_settings` (entered for the call where
    the caller has not). Cached: one compiled function per `fn`. During a call dynamo may compile
    `VARIANTS` graphs of it: each flag and dtype is one, all counted against one function's
    budget, and past dynamo's default 8 it would silently run eagerly."""
    kernel = torch.compile(fn, dynamic=True, options=INDUCTOR_OPTIONS)

    @functools.wraps(fn)
    def run(*args, **kwargs):
        with compile_settings():  # inside a render's block: set at its first compiled call only
            _set_for_block()
            return kernel(*args, **kwargs)

    return run


def exact_kernel(fn: Callable, what: str) -> Callable:
    """`fn` under torch.compile (dynamic shapes) for the "exact" mode, whose compiled output is
    `fn`'s own: where it cannot be compiled (no C++ compiler, an unsupported platform) the first
    call warns once, naming `what`, and every call runs `fn` eagerly, so a default that compiles
    ("auto") never fails where eager runs. An error eager raises too is raised as it is."""
    kernel = compiled(fn)
    failed = []

    def run(*args, **kwargs):
        if failed:
            return fn(*args, **kwargs)
        try:
            return kernel(*args, **kwargs)
        except Exception as error:  # inductor's errors have no common base short of Exception
            try:
                result = fn(*args, **kwargs)
            except Exception:
                raise error from None  # eager fails too: the call's error, not the compiler's
            failed.append(error)
            first = str(error).strip().splitlines()[0] if str(error).strip() else ""
            warnings.warn(f"torchvol: {what} could not be compiled ({type(error).__name__}: {first}); it runs "
                          "eagerly, with the same results", RuntimeWarning, stacklevel=2)
            return result

    return run
