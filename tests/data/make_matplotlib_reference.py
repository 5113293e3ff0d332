"""Regenerate ``matplotlib_reference.npz``: Simple Shapes images drawn with matplotlib the way the public
dataset generator draws them (a patch per shape on a 32x32-pixel figure at dpi 1, black axes, y up,
axes limits 0-32, PNG round trip), for the renderer test in ``tests/test_simple_shapes.py``.

Needs matplotlib, which the project itself does not use:
``pip install matplotlib && python tests/data/make_matplotlib_reference.py``.
"""

import io
import sys
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import patches  # noqa: E402
from matplotlib import path as mpath  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from envs.simple_shapes import _EGG_BEZIER, sample_states, shape_polygon  # noqa: E402


def matplotlib_image(cls, x, y, size, rotation, rgb) -> np.ndarray:
    fig, ax = plt.subplots(figsize=(32, 32), dpi=1)
    colour = np.asarray(rgb, np.float32) / 255
    if cls == 1:  # the egg is a closed path of four cubic Bezier curves
        c, s = np.cos(rotation), np.sin(rotation)
        p = _EGG_BEZIER - 0.5
        v = np.array([x, y]) + size * np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], 1)
        codes = [mpath.Path.MOVETO] + [mpath.Path.CURVE4] * 12
        patch = patches.PathPatch(mpath.Path(v, codes), facecolor=colour)
    else:
        patch = patches.Polygon(shape_polygon(cls, x, y, size, rotation), facecolor=colour)
    ax.add_patch(patch)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.grid(False)
    ax.set_xlim(0, 32)
    ax.set_ylim(0, 32)
    ax.set_facecolor("black")
    plt.tight_layout(pad=0)
    buf = io.BytesIO()
    plt.savefig(buf, dpi=1, format="png")
    plt.close(fig)
    buf.seek(0)
    return np.round(plt.imread(buf)[..., :3] * 255).astype(np.uint8)


if __name__ == "__main__":
    n = 60
    st = sample_states(np.random.default_rng(123), n)
    images = np.stack(
        [
            matplotlib_image(st["cls"][i], *st["pos"][i], st["size"][i], st["rotation"][i], st["rgb"][i])
            for i in range(n)
        ]
    )
    np.savez_compressed(Path(__file__).with_name("matplotlib_reference.npz"), image=images, **st)
    print(f"wrote {n} images")
