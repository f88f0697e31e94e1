"""Run GLSL fragment shaders on Mesa llvmpipe (moderngl, EGL) — the oracle for parity tests.

`run_fragment` renders one full-screen quad with a ``#version 330`` fragment shader and reads the
framebuffer back as an ``(H, W, 4)`` numpy array whose row 0 is the TOP of the picture (OpenGL's
row 0 is the bottom, so the read-back is flipped). ``gl_FragCoord.xy`` of the pixel at array index
``[i, j]`` is ``(j + 0.5, H - 1 - i + 0.5)``.

ShaderToy-style code (``void mainImage(out vec4, in vec2)``) runs through `shadertoy_source`, which
declares ``iResolution``, ``iTime``, ``iMouse`` and ``iChannel0..3``; `run_fragment` sets
``iResolution`` to ``(W, H, 1)`` when the program uses it and the caller did not.

moderngl is imported inside the functions, so ``import torchvol.measure.glsl`` works without it;
`gl_context` returns None (never raises) when no context can be made, and tests skip on None.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np

_CTX: Any = None
_CTX_FAILED = False

_VERTEX = """
#version 330
in vec2 in_pos;
void main() { gl_Position = vec4(in_pos, 0.0, 1.0); }
"""

_SHADERTOY_HEADER = """#version 330
uniform vec3 iResolution;
uniform float iTime;
uniform float iTimeDelta;
uniform int iFrame;
uniform vec4 iMouse;
uniform sampler2D iChannel0;
uniform sampler2D iChannel1;
uniform sampler2D iChannel2;
uniform sampler2D iChannel3;
out vec4 outColor;
"""

_SHADERTOY_FOOTER = """
void main() { mainImage(outColor, gl_FragCoord.xy); }
"""


def gl_context():
    """The cached standalone EGL context (Mesa llvmpipe here), or None if none can be made."""
    global _CTX, _CTX_FAILED
    if _CTX is not None or _CTX_FAILED:
        return _CTX
    try:
        import moderngl

        _CTX = moderngl.create_standalone_context(backend="egl")
    except Exception:  # missing module, no EGL, no driver: tests skip
        _CTX_FAILED = True
        _CTX = None
    return _CTX


def renderer_name() -> str | None:
    """``GL_RENDERER`` of the context (e.g. ``"llvmpipe (LLVM 15.0.6, 256 bits)"``), or None."""
    ctx = gl_context()
    return None if ctx is None else ctx.info.get("GL_RENDERER")


def shadertoy_source(body: str) -> str:
    """Wrap ShaderToy code (defines ``mainImage``) into a complete ``#version 330`` shader."""
    return _SHADERTOY_HEADER + "\n" + body + "\n" + _SHADERTOY_FOOTER


class _Pass:
    """Compiled program, quad, textures and framebuffer for one shader at one size."""

    def __init__(self, source, width, height, uniforms, textures, float_output):
        import moderngl

        ctx = gl_context()
        if ctx is None:
            raise RuntimeError("no OpenGL context (moderngl/EGL unavailable)")
        if width <= 0 or height <= 0:
            raise ValueError(f"width, height: got {(width, height)!r}; positive integers")
        self.ctx = ctx
        self.width, self.height = int(width), int(height)
        self.float_output = float_output
        self.prog = ctx.program(vertex_shader=_VERTEX, fragment_shader=source)
        quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype="f4")
        self.vbo = ctx.buffer(quad.tobytes())
        self.vao = ctx.vertex_array(self.prog, [(self.vbo, "2f", "in_pos")])
        uniforms = dict(uniforms or {})
        if "iResolution" in self.prog and "iResolution" not in uniforms:
            uniforms["iResolution"] = (float(width), float(height), 1.0)
        for name, value in uniforms.items():
            if name not in self.prog:  # unused uniforms are optimised out: ignore them
                continue
            v = np.asarray(value).ravel().tolist()
            self.prog[name].value = v[0] if len(v) == 1 else tuple(v)
        self.textures = []
        for unit, (name, array) in enumerate((textures or {}).items()):
            arr = np.ascontiguousarray(np.asarray(array))
            if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 4:
                raise ValueError(
                    f"textures[{name!r}]: got dtype {arr.dtype}, shape {arr.shape}; "
                    "uint8 array (H, W, 4) indexed [y, x, channel]"
                )
            tex = ctx.texture((arr.shape[1], arr.shape[0]), 4, arr.tobytes(), dtype="f1")
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x = True
            tex.repeat_y = True
            self.textures.append((unit, tex))
            if name in self.prog:
                self.prog[name].value = unit
        dtype = "f4" if float_output else "f1"
        self.color = ctx.texture((self.width, self.height), 4, dtype=dtype)
        self.fbo = ctx.framebuffer(color_attachments=[self.color])

    def draw(self):
        self.fbo.use()
        self.ctx.viewport = (0, 0, self.width, self.height)
        for unit, tex in self.textures:
            tex.use(location=unit)
        self.vao.render(mode=self._strip())
        self.ctx.finish()

    @staticmethod
    def _strip():
        import moderngl

        return moderngl.TRIANGLE_STRIP

    def read(self) -> np.ndarray:
        dtype = "f4" if self.float_output else "f1"
        raw = self.fbo.read(components=4, dtype=dtype)
        arr = np.frombuffer(raw, dtype=np.float32 if self.float_output else np.uint8)
        arr = arr.reshape(self.height, self.width, 4)[::-1]
        if not self.float_output:
            arr = arr.astype(np.float32) / 255.0
        return np.ascontiguousarray(arr)

    def release(self):
        for obj in (self.fbo, self.color, self.vao, self.vbo, self.prog):
            obj.release()
        for _, tex in self.textures:
            tex.release()


def run_fragment(
    source: str,
    width: int,
    height: int,
    *,
    uniforms: dict | None = None,
    textures: dict[str, np.ndarray] | None = None,
    float_output: bool = True,
) -> np.ndarray:
    """Render a full-screen quad with fragment shader `source`; return float32 ``(H, W, 4)``.

    source: a complete ``#version 330`` fragment shader with one ``out vec4`` (see
        `shadertoy_source` for ShaderToy code).
    uniforms: name -> value (scalar or sequence); names the program does not use are ignored.
    textures: sampler name -> uint8 array ``(h, w, 4)`` indexed ``[y, x, channel]`` (row 0 is
        v≈0, as OpenGL uploads it); bound to units 0, 1, ... with LINEAR min/mag filtering (no
        mipmaps) and REPEAT wrap.
    float_output: True renders to RGBA32F (exact shader floats); False to RGBA8 (what a display
        sees), returned as float32 in [0, 1] (k/255).
    Returns ``(H, W, 4)`` float32 with row 0 the TOP of the picture.
    """
    p = _Pass(source, width, height, uniforms, textures, float_output)
    try:
        p.draw()
        return p.read()
    finally:
        p.release()


def time_fragment(
    source: str,
    width: int,
    height: int,
    *,
    uniforms: dict | None = None,
    textures: dict[str, np.ndarray] | None = None,
    float_output: bool = False,
    repeat: int = 5,
    warmup: int = 1,
) -> float:
    """Median wall time in seconds of one render (draw + ``ctx.finish()``), over `repeat` runs.

    Compilation, uploads and `warmup` untimed draws happen first, so the figure is the steady
    per-frame cost of the shader on this context (llvmpipe: all CPU threads it was given).
    """
    if repeat < 1:
        raise ValueError(f"repeat: got {repeat!r}; an integer >= 1")
    p = _Pass(source, width, height, uniforms, textures, float_output)
    try:
        for _ in range(warmup):
            p.draw()
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            p.draw()
            times.append(time.perf_counter() - t0)
        return statistics.median(times)
    finally:
        p.release()
