"""Test-wide set-up: MuJoCo must pick its headless GL back-end before anything imports mujoco."""

import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root (envs/, scripts)
