"""Whether a render runs compiled kernels: the `compile` setting of `render`, `generate` and
`SceneDataset`, and whether Dr.Jit can run them here. One compiler builds every kernel: Dr.Jit's
LLVM backend (the marches, `volume.kernel_march`; the voxel walk, `voxel.walk.drjit_traverse`;
the terrain's tracing, `terrain.trace_kernel`), in under a second, cached on disk. (torch.compile's
inductor kernels were removed: Dr.Jit measured 1.6–1.9× faster than inductor's fused kernel on
the same points, builds in under a second against ~65 s cold, and one backend means one source;
docs/SPEED.md.)

* ``"kernels"`` (``True``, the default): Dr.Jit's kernels wherever the plan finds one for a
  technique and Dr.Jit runs (float32 on the CPU, libLLVM present); the rest eager. Their output
  is the canonical one; it agrees with eager within the tolerances of
  tests/volume/test_kernel_march.py, not bitwise.
* ``"off"`` (``False``, ``None``, ``--eager``): every kernel eager: the reference, on any device
  and dtype; recorded in a generated dataset's meta.json (``"eager": true``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from ..schema.validate import fail

__all__ = ["CompileMode", "compile_mode", "drjit_available", "traced", "traced_columns", "traced_vectors"]

CompileMode = Literal["kernels", "off"]
MODES = ("kernels", "off")


def compile_mode(value, *, path: str = "compile") -> CompileMode:
    """`value` (True or "kernels"; False, None or "off") as a mode name. Raises ValueError naming
    `path`, the value and the allowed values otherwise."""
    if value is None:
        return "off"
    if isinstance(value, (bool, np.bool_)):
        return "kernels" if value else "off"
    if not isinstance(value, str) or value not in MODES:
        fail(path, value, "expected " + " or ".join(repr(m) for m in MODES) + " (or True for kernels, False or None for off)")
    return value


def traced(fn, like: torch.Tensor) -> list[torch.Tensor]:
    """`fn(lane)` run as one Dr.Jit kernel (`lane`: a tensor [n] -> Dr.Jit float32 lanes; `fn`
    written in lanes, `ops.lanes`): its list of lanes back as tensors [n] of `like`'s dtype and device."""
    return traced_columns(fn, like)


def traced_vectors(fn, like: torch.Tensor) -> torch.Tensor:
    """`traced` of an `fn(lane)` giving three lanes, written interleaved by the kernel -> one tensor
    [n, 3] of `like`'s dtype and device (no column stacked in torch: a float32 [65 k, 3] stack is
    ~0.3 ms)."""
    return traced_columns(fn, like, (3,))[0]


def traced_columns(fn, like: torch.Tensor, widths: tuple[int, ...] | None = None, also=None) -> list[torch.Tensor]:
    """`traced` of an `fn(lane)` giving sum(`widths`) lanes, one kernel: each group of 3 lanes one
    tensor [n, 3] written interleaved (as `traced_vectors`), a group of 1 a tensor [n], of `like`'s
    dtype and device (`widths` None: every lane a tensor [n]). `also()`: more lanes the same kernel
    evaluates (counts the caller reads after it), traced after `fn`."""
    import drjit as dr

    from ..ops.lanes import floats_of, interleaved, tensor_of
    from .threads import set_drjit_threads

    set_drjit_threads()
    values, out, k = fn(floats_of), [], 0
    widths = (1,) * len(values) if widths is None else widths
    for w in widths:
        if w not in (1, 3):
            raise ValueError(f"traced_columns: a group of {w} lanes; groups are 1 or 3 wide")
        out.append(values[k] if w == 1 else interleaved(values[k:k + 3]))
        k += w
    dr.eval(out, [] if also is None else also())
    tensors = [tensor_of(x).to(like) for x in out]
    return [t if w == 1 else t.view(-1, 3) for t, w in zip(tensors, widths)]


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
