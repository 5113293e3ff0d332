"""Bundle the VAEs and GW of a pretrain_vae_gw.py run into envs/pretrained/<env>/, where the agent scripts
find them on a fresh clone: the weights in float16 (read back as float32 by load_state_dict), the
held-out samples they were evaluated on, and a JSON record (command, code version, files' SHA-256 and
the held-out figures recomputed from the float16 weights, which tests/test_bundled_pretrained.py
reproduces).

    python benchmarks/bundle_pretrained.py --env robodesk --made "2-core AMD EPYC CPU, 84 min"
"""

import hashlib
import json
import subprocess
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import pretrain_vae_gw as P  # noqa: E402


@dataclass
class Args:
    env: str = "robodesk"
    """environment of the checkpoints"""
    checkpoint_dir: str = "checkpoints"
    """where pretrain_vae_gw.py wrote <env>/vae.pt and <env>/gw.pt"""
    data_dir: str = "data"
    """where it read its data (the held-out samples are the first ones)"""
    command: str = "python pretrain_vae_gw.py --env robodesk --cpu-preset"
    """the command that made the checkpoints (recorded)"""
    made: str = ""
    """hardware and time of the run (recorded)"""
    overwrite: bool = False
    """replace a bundle that exists"""


def half(state: dict) -> dict:
    """Floating-point tensors as float16; integer buffers (BatchNorm's counters) as they are."""
    return {k: v.half() if torch.is_floating_point(v) else v for k, v in state.items()}


def held_out_figures(bundle: Path, env: str) -> dict:
    """The held-out figures of the bundled (float16) weights on the bundled held-out samples."""
    vae_v, vae_attr, vae_ck = P.load_vaes(bundle / "vae.pt", env)
    gw_ck = torch.load(bundle / "gw.pt", map_location="cpu", weights_only=False)
    with np.load(bundle / "held_out.npz") as d:
        images, attrs = d["image"], d["attr"]
    attrs_n = ((attrs - vae_ck["attr_mean"]) / vae_ck["attr_std"]).astype(np.float32)
    with torch.no_grad():
        x, a = P.images_to_tensor(images, "cpu"), torch.as_tensor(attrs_n)
        figures = {
            "recon_mse_v": torch.nn.functional.mse_loss(vae_v.decode(vae_v.encode(x)[0]), x).item(),
            "recon_mse_attr": torch.nn.functional.mse_loss(vae_attr.decode(vae_attr.encode(a)[0]), a).item(),
        }
    spec = P.ENV_SPECS[env]
    gw = P.GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"])
    gw.load_state_dict(gw_ck["gw"])
    gw.eval()
    u_v, u_a = P.encode_unimodal(vae_v, vae_attr, images, attrs_n, "cpu")
    silent = types.SimpleNamespace(add_images=lambda *a, **k: None, add_scalar=lambda *a, **k: None)
    args = types.SimpleNamespace(env=env)
    return figures | P.evaluate_gw(
        args, gw, vae_v, vae_attr, vae_ck, images, attrs, u_v, u_a, len(attrs), silent
    )


def main(a: Args) -> None:
    src = Path(a.checkpoint_dir) / a.env
    bundle = ROOT / "envs" / "pretrained" / a.env
    if bundle.exists() and not a.overwrite:
        raise SystemExit(f"{bundle} exists: add --overwrite to replace it")
    bundle.mkdir(parents=True, exist_ok=True)
    vae = torch.load(src / "vae.pt", map_location="cpu", weights_only=False)
    gw = torch.load(src / "gw.pt", map_location="cpu", weights_only=False)
    if "vae_digest" not in gw:  # a GW made before pretrain_vae_gw.py recorded its VAE's digest
        vae_v, vae_attr, _ = P.load_vaes(src / "vae.pt", a.env)
        made_on = gw["identity"]["vae_fingerprint"]  # the sum of the VAE's weights it was trained on
        now = float(sum(p.double().sum() for p in [*vae_v.parameters(), *vae_attr.parameters()]))
        if abs(made_on - now) > 1e-9 * max(1.0, abs(now)):
            raise SystemExit(f"{src / 'gw.pt'} was trained on another VAE than {src / 'vae.pt'}")
        gw["vae_digest"] = P.vae_digest(vae)
    vae["vae_v"], vae["vae_attr"], gw["gw"] = half(vae["vae_v"]), half(vae["vae_attr"]), half(gw["gw"])
    gw["vae_checkpoint"] = f"envs/pretrained/{a.env}/vae.pt"
    torch.save(vae, bundle / "vae.pt")
    torch.save(gw, bundle / "gw.pt")
    n_eval = vae["data"]["eval_samples"]
    data = P.InMemory(Path(a.data_dir) / a.env, a.env, n_eval)
    images, attrs = data.held_out(n_eval)
    np.savez_compressed(bundle / "held_out.npz", image=images, attr=attrs)
    figures = held_out_figures(bundle, a.env)
    code = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT)
    record = {
        "command": a.command,
        "code": code.stdout.strip(),
        "made": a.made,
        "data": vae["data"]["samples_per_source_and_task"],
        "render_quality": gw["args"]["render_quality"],
        "files": {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(bundle.iterdir())},
        "held_out": figures,
    }
    (bundle.parent / f"{a.env}.json").write_text(json.dumps(record, indent=1))
    size = sum(f.stat().st_size for f in bundle.iterdir()) / 2**20
    print(f"wrote {bundle} ({size:.1f} MiB) and {bundle.parent / f'{a.env}.json'}")


if __name__ == "__main__":
    main(tyro.cli(Args))
