"""A 4096×4096 render peaks under 2 GB RSS: chunked rendering keeps the working set to one chunk
on top of the full-frame outputs. Measured by tools/peak_rss.py in a fresh subprocess, on the
closed-form homogeneous box (a real volume, and the cheapest scene at this size)."""

import importlib.util
from pathlib import Path

SPEC = importlib.util.spec_from_file_location("peak_rss", Path(__file__).resolve().parents[1] / "tools" / "peak_rss.py")
peak_rss = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(peak_rss)


def test_4096_render_peak_rss_under_2gb():
    m = peak_rss.measure(preset="homogeneous-box", size=4096, threads=1)
    assert m["peak_rss_bytes"] < 2e9, (
        f"peak RSS {m['peak_rss_bytes'] / 1e9:.2f} GB >= 2 GB for a 4096×4096 render "
        f"(outputs {m['output_bytes'] / 1e9:.2f} GB, render {m['render_s']:.1f} s)")
