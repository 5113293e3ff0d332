"""Regenerate ``pillow_lanczos_reference.npz``: a random 120x120 render cropped and resized to 64x64 by
Pillow exactly as the original RoboDesk does (``Image.crop(box).resize((64, 64), LANCZOS)``), for the
image-pipeline test in ``tests/test_robodesk.py``. Needs Pillow, which the project itself does not use:
``pip install pillow && python tests/data/make_pillow_reference.py``.
"""

from pathlib import Path

import numpy as np
from PIL import Image

CROP_BOX = (16.75, 25.0, 105.0, 88.75)

if __name__ == "__main__":
    render = np.random.default_rng(0).integers(0, 256, (120, 120, 3), dtype=np.uint8)
    image = np.asarray(Image.fromarray(render).crop(box=CROP_BOX).resize([64, 64], resample=Image.LANCZOS))
    np.savez_compressed(Path(__file__).with_name("pillow_lanczos_reference.npz"), render=render, image=image)
