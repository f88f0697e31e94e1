"""Elementwise maths written once for two backends: torch tensors (the eager reference: any
device, float64 too) and Dr.Jit's LLVM arrays (the compiled kernels, `volume.kernel_march`).

A technique written with Python's operators and these functions — one value per lane, a vector
as three lanes, a colour as three — runs as either: called with torch tensors of shape [n] it is
the eager code, called with Dr.Jit `Float`/`Int32` arrays inside a `drjit.while_loop` it is traced
into the kernel. Python numbers mix with both. That is how the renderer keeps one source per
technique and no hand-kept twin of it (docs/SPEED.md, "One source"). Each function picks its
backend from its array arguments; the results agree within float rounding (the Dr.Jit forms of
`expm1` and `lerp` are written out below to match torch's)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch

Lane = object  # a torch Tensor [n], a Dr.Jit array of n lanes, or a Python number


def _is_torch(*xs) -> bool:
    for x in xs:  # (a loop, not any() over a generator: half the time, on every lane op a kernel traces)
        if isinstance(x, torch.Tensor):
            return True
    return False


def _is_number(*xs) -> bool:
    return all(isinstance(x, (int, float)) for x in xs)


def where(cond, a, b):
    """`a` where `cond`, else `b` (torch.where / drjit.select)."""
    if _is_torch(cond, a, b):
        return torch.where(cond, a, b)
    import drjit as dr

    return dr.select(cond, a, b)


def int_like(value: int, like):
    """The integer `value` where `like` is a Dr.Jit array (an Int32 lane), else the number itself."""
    if _is_torch(like) or _is_number(like):
        return value
    from drjit.llvm import Int32

    return Int32(value)


def _unary(name: str, number=None, doc: str = ""):
    """The lane function `name` of torch and Dr.Jit alike (`number`: its form on a Python number)."""

    def fn(x):
        if number is not None and _is_number(x):
            return number(x)
        if _is_torch(x):
            return getattr(torch, name)(x)
        import drjit as dr

        return getattr(dr, name)(x)

    fn.__name__, fn.__doc__ = name, doc
    return fn


exp = _unary("exp", math.exp, "e^x.")
log = _unary("log", None, "The natural logarithm.")
log2 = _unary("log2", None, "The base-2 logarithm.")
sqrt = _unary("sqrt", math.sqrt, "The square root.")
floor = _unary("floor", None, "Rounded down to an integer value (still a float).")
ceil = _unary("ceil", None, "Rounded up to an integer value (still a float).")
isfinite = _unary("isfinite", math.isfinite, "Neither infinite nor NaN.")
abs = _unary("abs", math.fabs, "|x|.")  # noqa: A001  the lane form of the builtin
sin = _unary("sin", math.sin, "The sine.")
cos = _unary("cos", math.cos, "The cosine.")
tan = _unary("tan", math.tan, "The tangent.")
round = _unary("round", None, "To the nearest integer value, ties to even (torch.round, drjit.round).")  # noqa: A001  the lane form of the builtin


def sqrt_rounded(x):
    """The square root correctly rounded in x's float type, as Dr.Jit's is: torch's float32 sqrt
    (this build's) is not, 17% of values an ulp off, so on torch float32 it is taken in float64
    and rounded (torch's float64 sqrt is within an ulp of float64, far inside the half float32 ulp
    this rounding needs but in ~2⁻²⁹ of cases). Where eager and kernel must be the same bits."""
    if _is_torch(x) and x.dtype == torch.float32:
        return torch.sqrt(x.double()).float()
    return sqrt(x)


def expm1(x):
    """e^x − 1 without cancellation near 0. Dr.Jit has no expm1: Kahan's form (u − 1)·x / ln u,
    exact to a few ulps, with its limits written out (u = 1: x; u − 1 = −1: −1)."""
    if _is_torch(x):
        return torch.expm1(x)
    import drjit as dr

    u = dr.exp(x)
    um1 = u - 1.0
    kahan = um1 * x / dr.log(dr.select(u == 1.0, 2.0, u))
    return dr.select(u == 1.0, x, dr.select(um1 == -1.0, -1.0, dr.select(dr.isinf(u), u, kahan)))


def atan(x):
    """The arctangent, in [−π/2, π/2]. Dr.Jit's own does not compile under this machine's LLVM 15
    (a constant-pool load it cannot select): Cephes' atanf there, its range reduced to
    |x| ≤ tan(π/8) and a degree-9 odd polynomial (relative error ~1e-7)."""
    if _is_number(x):
        return math.atan(x)
    if _is_torch(x):
        return torch.atan(x)
    a = abs(x)
    big = a > 2.414213562373095  # tan(3π/8)
    mid = (a > 0.41421356237309503) & ~big  # tan(π/8)
    r = where(big, -1.0 / a, where(mid, (a - 1.0) / (a + 1.0), a))
    z = r * r
    y = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z * r + r
    out = where(big, math.pi / 2, where(mid, math.pi / 4, 0.0)) + y
    return where(x < 0.0, -out, out)


def minimum(a, b):
    """The smaller of `a` and `b` (selects in Dr.Jit: LLVM 15 cannot lower its min intrinsics)."""
    if _is_number(a, b):
        return min(a, b)
    if _is_torch(a, b):
        if _is_number(a) or _is_number(b):  # a Python number keeps its precision in a float64 render
            return b.clamp_max(a) if _is_number(a) else a.clamp_max(b)
        return torch.minimum(a, b)
    import drjit as dr

    return dr.select(b < a, b, a)


def maximum(a, b):
    """The larger of `a` and `b`."""
    if _is_number(a, b):
        return max(a, b)
    if _is_torch(a, b):
        if _is_number(a) or _is_number(b):
            return b.clamp_min(a) if _is_number(a) else a.clamp_min(b)
        return torch.maximum(a, b)
    import drjit as dr

    return dr.select(b > a, b, a)


def clamp_min(x, lo: float):
    """max(x, lo), NaN passing through."""
    if _is_torch(x):
        return x.clamp_min(lo)
    import drjit as dr

    return dr.select(x < lo, lo, x)


def clamp_max(x, hi: float):
    """min(x, hi), NaN passing through."""
    if _is_torch(x):
        return x.clamp_max(hi)
    import drjit as dr

    return dr.select(x > hi, hi, x)


def clamp(x, lo: float, hi: float):
    """clamp_max then clamp_min, NaN passing through as torch's."""
    if _is_torch(x):
        return x.clamp(lo, hi)
    return clamp_min(clamp_max(x, hi), lo)


def lerp(a, b, w):
    """a + w·(b − a) as torch.lerp's vectorised CPU kernel computes it: a fused multiply-add from
    the nearer end (exactly `b` at w = 1)."""
    if _is_torch(a, b, w):
        if not isinstance(w, torch.Tensor):
            return torch.lerp(a, b, w)
        return torch.lerp(torch.as_tensor(a, dtype=w.dtype), torch.as_tensor(b, dtype=w.dtype), w)
    import drjit as dr

    small = dr.abs(w) < 0.5
    return dr.fma(dr.select(small, w, w - 1.0), b - a, dr.select(small, a, b))


def divide(x, n: float):
    """x / n, correctly rounded on both backends: Dr.Jit turns a division by a Python number into
    a multiplication by its reciprocal (an ulp off a third of the time), not by an array (here a
    kernel parameter, `drjit.opaque`)."""
    if _is_torch(x) or _is_number(x):
        return x / n
    import drjit as dr

    return x / dr.opaque(type(x), n)


def full_like(x, value: float):
    """`value` in every lane of `x`."""
    if _is_torch(x):
        return torch.full_like(x, value)
    import drjit as dr

    return dr.full(type(x), value, dr.width(x))


def tiny(x) -> float:
    """The smallest normal number of `x`'s float type (float32 for Dr.Jit's Float)."""
    if _is_torch(x):
        return torch.finfo(x.dtype).tiny
    return float(torch.finfo(torch.float32).tiny)


def to_int32(x):
    """Truncated towards 0 to int32 (the lattice noises' cell index after a floor)."""
    if _is_torch(x):
        return x.to(torch.int32)
    from drjit.llvm import Int32

    return Int32(x)


def remainder(i, n: int):
    """i mod n of int lanes `i` and a positive int `n`, in [0, n) as torch.remainder (floor
    division's remainder; Dr.Jit's ``%`` truncates towards 0, so a negative remainder is shifted)."""
    if _is_torch(i):
        return torch.remainder(i, n)
    import drjit as dr

    r = i % n
    return dr.select(r < 0, r + n, r)


def to_float(i, like):
    """Int lanes `i` as floats of `like`'s type."""
    if _is_torch(i):
        return i.to(like.dtype)
    from drjit.llvm import Float

    return Float(i)


def floats_of(t: torch.Tensor):
    """A torch tensor [n] as Dr.Jit float32 lanes: a kernel's input, on the CPU. Dr.Jit maps the
    array it is given: a float32 contiguous CPU tensor's own memory (read when the kernel runs),
    else a float32 copy."""
    from drjit.llvm import Float

    if t.dtype is torch.float32 and t.device.type == "cpu" and t.is_contiguous():  # (3 us, not 7: it is the common case)
        return Float(t.detach().numpy())
    return Float(t.detach().to(torch.float32).contiguous().cpu().numpy())


def tensor_of(x) -> torch.Tensor:
    """Dr.Jit lanes (evaluated: a kernel's output) as a CPU tensor [n] of their type, sharing their
    memory (DLPack: no copy; `floats_of`'s inverse)."""
    return torch.from_dlpack(x)


def interleaved(columns: list):
    """C Dr.Jit lanes as one array of their rows laid flat (row i's C values together), for the
    kernel that evaluates them to write: `rows_of` reads it back as a tensor [n, C]. Stacking C
    columns in torch instead writes strided rows (a float32 [65 k, 3] stack: ~0.25 ms)."""
    import drjit as dr
    from drjit.llvm import ArrayXf

    return dr.ravel(ArrayXf(list(columns)))


def rows_of(flat, channels: int) -> torch.Tensor:
    """`interleaved`'s array, evaluated, as a CPU tensor [n, channels] sharing its memory."""
    return tensor_of(flat).view(-1, channels)


def ints_of(t: torch.Tensor):
    """A torch integer (or bool) tensor [n] as Dr.Jit int32 lanes, on the CPU (an int32 contiguous
    CPU tensor's own memory, as `floats_of`, else an int32 copy)."""
    from drjit.llvm import Int32

    return Int32(t.detach().to(torch.int32).contiguous().cpu().numpy())


def lanes_of(value: torch.Tensor, gather):
    """Per-ray lanes of a per-ray tensor [n] or [n, C] (a list of C lanes)."""
    return gather(value) if value.ndim == 1 else [gather(value[:, c]) for c in range(value.shape[1])]


def vector_lanes(t: torch.Tensor) -> list:
    """Vectors [n, 3] as three Dr.Jit float32 lanes read from their rows as they lie (unravelled in
    the kernel: no column copied out in torch, ~45 µs each at 65 k)."""
    import drjit as dr
    from drjit.llvm import Array3f

    v = dr.unravel(Array3f, floats_of(t.reshape(-1)))
    return [v[0], v[1], v[2]]


def row_lanes(idx: torch.Tensor):
    """A kernel's reader of rows `idx` [n] of per-ray tensors: of(x), x [R] or [R, C] float, -> a
    lane, or a list of C, of its rows idx gathered in the kernel from x as it lies (one copy into
    Dr.Jit: no index_select and C column copies in torch first)."""
    import drjit as dr
    from drjit.llvm import Float, UInt32

    rows = UInt32(idx.to(torch.int32).cpu().numpy())

    def of(x: torch.Tensor):
        flat = floats_of(x.reshape(-1))
        if x.ndim == 1:
            return dr.gather(Float, flat, rows)
        width = x.shape[1]
        return [dr.gather(Float, flat, rows * width + c) for c in range(width)]

    return of


def per_scene_lanes(s: torch.Tensor):
    """per scene (B,) or (B, C) -> the lanes of rays of scenes `s` [n], gathered in the kernel from
    the B values: a table of B floats a value, not n floats made and copied in torch first (a
    look's ~30 values were ~10% of a template render's time around its kernel)."""
    import drjit as dr
    from drjit.llvm import Float, UInt32

    scene = UInt32(s.to(torch.int32).cpu().numpy())
    return lambda x: lanes_of(x, lambda v: dr.gather(Float, floats_of(v), scene))


def lanes_inputs(s: torch.Tensor, per_ray) -> SimpleNamespace:
    """How a kernel's inputs are made for lanes of scenes `s` [n] (a density's, `fields.DENSITIES`'
    ``lanes``; the terrain's): per scene -> per lane (`per_lane`, e.g. `per_scene_lanes(s)`), int
    and float tables, numbers as kernel parameters."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    return SimpleNamespace(per_lane=per_ray, scene=s.cpu(), ints=lambda t: Int32(t.to(torch.int32).numpy()),
                           floats=lambda t: Float(t.to(torch.float32).numpy()), number=lambda c: dr.opaque(Float, float(c)))


def gather(table, index):
    """`table[index]`: a 1-D table (a torch tensor, or a Dr.Jit array of the lanes' type) at int32
    lanes `index` (values in range)."""
    if _is_torch(table, index):
        return table.index_select(0, index)
    import drjit as dr
    from drjit.llvm import UInt32

    return dr.gather(type(table), table, UInt32(index))


def pairs_of(t: torch.Tensor):
    """A float32 table of pairs [M, 2] as `gather_pair` reads it in a kernel: each pair one 64-bit
    word (Dr.Jit UInt64 lanes, the first value in its low half)."""
    from drjit.llvm import UInt64

    return UInt64(t.detach().to(torch.float32).contiguous().cpu().view(torch.uint64).reshape(-1).numpy())


def gather_pair(table, index) -> tuple:
    """`table[index]`'s two values: a table of pairs (a torch tensor [M, 2], or `pairs_of`'s Dr.Jit
    words) at int32 lanes `index`. In a kernel one 64-bit gather a pair, not two 32-bit ones: two
    values read for about the cost of one (the 16 taps of a million bicubic sun-grid lookups:
    7.1 -> 4.9 ms; a 256² multi-layer's march kernel 85 -> 79 ms), the same bits."""
    if _is_torch(table, index):
        rows = table.index_select(0, index)
        return rows[:, 0], rows[:, 1]
    import drjit as dr
    from drjit.llvm import Float, UInt32, UInt64

    word = dr.gather(UInt64, table, UInt32(index))
    return (dr.reinterpret_array(Float, UInt32(word & 0xFFFFFFFF)), dr.reinterpret_array(Float, UInt32(word >> 32)))


def gather_quad(table, index) -> list:
    """The four values of row `index` of a table of quadruples laid flat (a torch tensor [4·M] or
    Dr.Jit float lanes of it) at int32 lanes `index`. In a kernel one packet gather a row (a 16-byte
    load a lane), not four 32-bit gathers: the terrain's planar value noise reads a cell's four
    corners with it (`noise.planar_value_lanes`), the same bits."""
    if _is_torch(table, index):
        return list(table.view(-1, 4).index_select(0, index).unbind(1))
    import drjit as dr
    from drjit.llvm import Array4f, UInt32

    row = dr.gather(Array4f, table, UInt32(index))
    return [row[0], row[1], row[2], row[3]]


def fori(count: int, state: list, body):
    """`state` after `count` steps of `state = body(i, state)`, i = 0, 1, ... as a float (`state`: a
    flat list of lanes). On torch a Python loop; on Dr.Jit one symbolic loop (`drjit.while_loop`),
    the body traced once rather than `count` times: a kernel's tracing and its code shrink by the
    count, the same values (i is a float lane there, exact for any count below 2**24)."""
    if _is_torch(*state) or _is_number(*state):
        for i in range(count):
            state = body(float(i), state)
        return state
    import drjit as dr
    from drjit.llvm import Float, Int32

    start = [dr.zeros(Int32, max(dr.width(x) for x in state)), *state]
    return while_loop(start, lambda i, *_: i < count, lambda i, *x: (i + 1, *body(Float(i), list(x))))[1:]


def while_loop(state: list, cond, body) -> list:
    """`state = body(state)` while any lane of `cond(state)` holds (`state`: a flat list of lanes;
    `body` must leave the lanes where `cond` is false as they are). On torch a Python loop over
    whole tensors; on Dr.Jit one symbolic loop (`drjit.while_loop`), each lane running until its
    own `cond` fails."""
    if _is_torch(*state):
        while bool(cond(*state).any()):
            state = list(body(*state))
        return state
    import drjit as dr

    return list(dr.while_loop(tuple(state), cond, lambda *x: tuple(body(*x)), mode="symbolic"))


def columns(x):
    """A per-point torch tensor as lanes: [n] as it is, [n, C] as its C columns."""
    return x if x.ndim == 1 else list(x.unbind(1))


def smoothstep01(x):
    """3x² − 2x³ of `x` clamped to [0, 1]: 0 at 0, 1 at 1, flat at both."""
    x = clamp(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def length3(x, y, z):
    """|(x, y, z)| of three lanes."""
    return sqrt(x * x + y * y + z * z)


def dot3(a, b):
    """a·b of two vectors of three lanes each (summed x, y, z in order)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


__all__ = ["abs", "atan", "clamp", "clamp_max", "clamp_min", "columns", "cos", "divide", "dot3", "exp", "expm1", "floor", "full_like", "gather", "gather_pair", "gather_quad", "length3", "lerp", "log",
           "floats_of", "fori", "int_like", "interleaved", "ints_of", "lanes_inputs", "lanes_of", "log2", "maximum", "minimum", "per_scene_lanes", "remainder", "round", "rows_of", "sin", "smoothstep01", "sqrt", "tan", "tiny", "to_float", "to_int32", "where", "while_loop"]
