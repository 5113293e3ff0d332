"""Convert agent checkpoints of an older layout to the current one, so gw_dreamer.py, gw_dreamer_e2e.py
and dreamer_baseline.py evaluate and resume them again:

- the loop state held the return scale as one float: it becomes a buffer of the agent (its EMA and its
  update count, one return-scale update per training update);
- a GW-Dreamer agent records no --done-head "on" / "off" (saved before the flag existed, or a bool of the
  experiments script's --no-done-head): it gets the value its weights show (a done head or none).

    python benchmarks/experiments/convert_checkpoint.py checkpoints/simple_shapes/agents/<run>.pt

Each file is rewritten in place, atomically, after a copy of the original is kept beside it as
``<file>.old`` (a file whose ``.old`` copy exists already is left alone). The converted run resumes
bit for bit as one saved in the current layout.
"""

from __future__ import annotations

import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro
from tyro.conf import Positional


@dataclass
class Args:
    checkpoints: Positional[tuple[str, ...]]
    """agent checkpoints of gw_dreamer.py, gw_dreamer_e2e.py or dreamer_baseline.py"""


GW_DREAMERS = ("gw_dreamer", "gw_dreamer_e2e")  # the kinds whose world model may lack a done head


def convert(path: Path) -> str:
    """Convert one checkpoint; a line that says what was done."""
    ck = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(ck, dict) or "state" not in ck or "agent" not in ck:
        raise SystemExit(f"error: {path} is no agent checkpoint of these scripts")
    scale = "return_scale" in ck["state"]
    done_head = ck.get("kind") in GW_DREAMERS and not isinstance(ck["args"].get("done_head"), str)
    if not (scale or done_head):
        return f"{path}: already in the current layout"
    backup = path.with_name(path.name + ".old")
    if backup.exists():
        raise SystemExit(f"error: {backup} exists; move it away to convert {path} again")
    state = ck["state"]
    if scale:
        ck["agent"]["return_scale.ema"] = torch.tensor([state.pop("return_scale")], dtype=torch.float64)
        ck["agent"]["return_scale.count"] = torch.tensor([float(state["updates"])], dtype=torch.float64)
    if done_head:
        ck["args"]["done_head"] = "on" if any(k.startswith("wm.done_head.") for k in ck["agent"]) else "off"
    shutil.copy2(path, backup)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(ck, tmp)
    os.replace(tmp, path)
    return f"{path}: converted (the original is kept as {backup})"


def main(args: Args) -> list[str]:
    lines = [convert(Path(p)) for p in args.checkpoints]
    print("\n".join(lines))
    return lines


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)) and 0)
