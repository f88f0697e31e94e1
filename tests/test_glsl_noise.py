"""Parity of torchvol.noise with the seed template's GLSL noise()/fbm run on Mesa llvmpipe.

The points are built in torch from gl_FragCoord with the shader's float32 op order, so the
comparison is of the noise alone. Measured (Mesa 22.3.6, llvmpipe LLVM 15): texture_noise with
the default llvmpipe filter emulation is bit-exact (max error 0); ideal float bilinear
(filter_bits=None) is off by up to ~5e-3 because llvmpipe filters RGBA8 in 8-bit fixed point.
"""

import numpy as np
import pytest
import torch

from torchvol.measure.glsl import gl_context, run_fragment, shadertoy_source
from torchvol.noise.lattice import default_noise_texture, fbm, texture_noise

pytestmark = [
    pytest.mark.gl,
    pytest.mark.skipif(gl_context() is None, reason="no OpenGL (moderngl/EGL) context"),
]

# measured max |torch - llvmpipe| over the grids below (bit-exact emulation)
TOL_NOISE = 0.0
TOL_FBM = 0.0

W, H = 96, 64
SCALE = 0.173
ZX = 0.0137

BODY = """
uniform vec3 uOffset;
float noise01(vec3 x) {
    vec3 p = floor(x); vec3 f = fract(x); f = f * f * (3.0 - 2.0 * f);
    vec2 uv = (p.xy + vec2(37.0, 239.0) * p.z) + f.xy;
    vec2 rg = textureLod(iChannel0, (uv + 0.5) / 256.0, 0.0).yx;
    return mix(rg.x, rg.y, f.z);
}
float noise(vec3 x) { return noise01(x) * 2.0 - 1.0; }
float fbm5(vec3 q, int lod) {
    float f;
    f = 0.50000 * noise(q); q *= 2.02;
    if (lod >= 2) f += 0.25000 * noise(q); q *= 2.03;
    if (lod >= 3) f += 0.12500 * noise(q); q *= 2.01;
    if (lod >= 4) f += 0.06250 * noise(q); q *= 2.02;
    if (lod >= 5) f += 0.03125 * noise(q);
    return f;
}
void mainImage(out vec4 o, in vec2 fc) {
    // one rounding chain per component: Mesa's NIR may reassociate chains of inexact adds
    // (measured: z = fc.x*a; z += fc.y*b; z + off  ran as (fc.x*a + off) + fc.y*b)
    vec3 x = vec3(fc * %(SCALE)s + uOffset.xy, (fc.x + fc.y * 96.0) * %(ZX)s + uOffset.z);
    int lod = int(fc.x) %% 6;
    o = vec4(noise01(x), fbm5(x, lod), fbm5(x, 5), x.z);
}
""" % {"ZX": repr(ZX), "SCALE": repr(SCALE)}


def torch_points(offset):
    """The shader's x for every pixel, [H*W, 3] float32, row 0 the top (like the read-back)."""
    f32 = torch.float32
    i, j = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    fc = torch.stack([j.to(f32) + 0.5, (H - 1 - i).to(f32) + 0.5], -1).reshape(-1, 2)
    off = torch.tensor(offset, dtype=f32)
    xy = fc * torch.tensor(SCALE, dtype=f32) + off[:2]
    z = (fc[:, 0] + fc[:, 1] * 96.0) * torch.tensor(ZX, dtype=f32) + off[2]
    x = torch.cat([xy, z[:, None]], 1)
    lod = (fc[:, 0].to(torch.int64)) % 6
    return x, lod


def report(got, want, what):
    err = (got.double() - want.double()).abs()
    k = int(err.argmax())
    return err.max().item(), f"{what}: max err {err.max().item():.3e} at pixel {divmod(k, W)}"


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.37), (1234.5, -987.25, 311.7), (-20000.3, 15000.1, -777.9)])
def test_noise_and_fbm_match_llvmpipe(offset):
    tex = default_noise_texture(3)
    out = run_fragment(
        shadertoy_source(BODY), W, H, uniforms={"uOffset": offset}, textures={"iChannel0": tex.numpy()}
    )
    gl = torch.from_numpy(out).reshape(-1, 4)
    x, lod = torch_points(offset)
    # the points themselves must agree exactly, or the comparison below is meaningless
    assert torch.equal(gl[:, 3], x[:, 2]), "point construction differs from the shader"

    n = texture_noise(x, tex)
    err, msg = report(n, gl[:, 0], "noise")
    assert err <= TOL_NOISE, msg

    def noise(q):
        return texture_noise(q, tex) * 2.0 - 1.0

    err, msg = report(fbm(x, noise, lod=lod), gl[:, 1], "fbm(lod)")
    assert err <= TOL_FBM, msg
    err, msg = report(fbm(x, noise), gl[:, 2], "fbm")
    assert err <= TOL_FBM, msg

    # without the fixed-point filter emulation the error is of the order of 1/255
    ideal = texture_noise(x, tex, filter_bits=None)
    err_ideal, _ = report(ideal, gl[:, 0], "ideal bilinear")
    assert 1e-4 < err_ideal < 2.0 / 255


def test_uint8_output_and_orientation():
    """RGBA8 output quantises to k/255; row 0 of the result is the top of the picture."""
    body = "void mainImage(out vec4 o, in vec2 fc) { o = vec4(fc.y / iResolution.y, 0.25, 0.0, 1.0); }"
    out = run_fragment(shadertoy_source(body), 4, 8, float_output=False)
    assert out.shape == (8, 4, 4) and out.dtype == np.float32
    assert out[0, 0, 0] > out[-1, 0, 0]  # top row has the largest fc.y
    assert np.allclose(out[..., 1], round(0.25 * 255) / 255)
    f = run_fragment(shadertoy_source(body), 4, 8)
    assert np.allclose(f[0, :, 0], 7.5 / 8) and np.allclose(f[-1, :, 0], 0.5 / 8)


BODY7 = BODY.split("void mainImage")[0] + """
float fbm7(vec3 q) {
    float f = 0.5 * noise(q); q *= 2.02;
    f += 0.25 * noise(q); q *= 2.03;
    f += 0.125 * noise(q); q *= 2.01;
    f += 0.0625 * noise(q); q *= 2.02;
    f += 0.03125 * noise(q); q *= 2.02;
    f += 0.015625 * noise(q); q *= 2.03;
    f += 0.0078125 * noise(q);
    return f;
}
void mainImage(out vec4 o, in vec2 fc) {
    vec3 x = vec3(fc * %(SCALE)s + uOffset.xy, (fc.x + fc.y * 96.0) * %(ZX)s + uOffset.z);
    o = vec4(fbm7(x), 0.0, 0.0, x.z);
}
""" % {"ZX": repr(ZX), "SCALE": repr(SCALE)}


def test_fbm7_constant_folding_model():
    """7 octaves (lacunarity cycled): Mesa folds the q *= chain; fold='mesa' must track it."""
    offset = (31.25, -7.5, 101.3)
    tex = default_noise_texture(5)
    out = run_fragment(
        shadertoy_source(BODY7), W, H, uniforms={"uOffset": offset}, textures={"iChannel0": tex.numpy()}
    )
    gl = torch.from_numpy(out).reshape(-1, 4)
    x, _ = torch_points(offset)
    assert torch.equal(gl[:, 3], x[:, 2])

    def noise(q):
        return texture_noise(q, tex) * 2.0 - 1.0

    err, msg = report(fbm(x, noise, octaves=7), gl[:, 0], "fbm7")
    assert err <= TOL_FBM, msg
    err_seq, _ = report(fbm(x, noise, octaves=7, fold="sequential"), gl[:, 0], "fbm7 sequential")
    assert err_seq > 1e-5  # the difference the folding model exists for


def test_time_fragment_returns_positive_median():
    from torchvol.measure.glsl import time_fragment

    body = "void mainImage(out vec4 o, in vec2 fc) { o = vec4(fc / iResolution.xy, 0.0, 1.0); }"
    t = time_fragment(shadertoy_source(body), 32, 32, repeat=3)
    assert 0.0 < t < 5.0
