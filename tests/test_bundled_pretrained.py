"""The Simple Shapes VAE + GW shipped in envs/pretrained/ (the main job's default on a fresh clone), and
what an agent script says when pre-trained checkpoints are missing."""

import json
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import AGENT_TINY, ROOT, run_cli

import gw_dreamer as G
import pretrain_vae_gw as P
from envs.simple_shapes import sample_dataset

BUNDLE = ROOT / "envs" / "pretrained" / "simple_shapes"
ROBODESK = ROOT / "envs" / "pretrained" / "robodesk"
sys.path.insert(0, str(ROOT / "benchmarks"))
from bundle_pretrained import held_out_figures  # noqa: E402


def test_the_bundle_reproduces_its_recorded_held_out_figures():
    """Re-draw the held-out samples (the first --eval-size samples of the seed-1 collection, as the
    pre-training drew them), and recompute every recorded figure from the shipped weights."""
    record = json.loads((BUNDLE.parent / "simple_shapes.json").read_text())
    vae_v, vae_attr, vae_ck = P.load_vaes(BUNDLE / "vae.pt", "simple_shapes")
    gw_ck = torch.load(BUNDLE / "gw.pt", map_location="cpu", weights_only=False)
    n_eval = vae_ck["data"]["eval_samples"]
    assert (n_eval, vae_ck["args"]["seed"], vae_ck["args"]["shard_size"]) == (2000, 1, 50_000)
    data = sample_dataset(50_000, seed=1 * 1_000_003)  # the first shard (collect's seeding)
    images, attrs = data["image"][:n_eval], data["attr"][:n_eval]
    attrs_n = ((attrs - vae_ck["attr_mean"]) / vae_ck["attr_std"]).astype(np.float32)
    with torch.no_grad():
        x, a = P.images_to_tensor(images, "cpu"), torch.as_tensor(attrs_n)
        figures = {
            "recon_mse_v": F.mse_loss(vae_v.decode(vae_v.encode(x)[0]), x).item(),
            "recon_mse_attr": F.mse_loss(vae_attr.decode(vae_attr.encode(a)[0]), a).item(),
        }
    spec = P.ENV_SPECS["simple_shapes"]
    gw = P.GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"])
    gw.load_state_dict(gw_ck["gw"])
    gw.eval()
    u_v, u_a = P.encode_unimodal(vae_v, vae_attr, images, attrs_n, "cpu")
    silent = types.SimpleNamespace(add_images=lambda *a, **k: None, add_scalar=lambda *a, **k: None)
    args = types.SimpleNamespace(env="simple_shapes")
    figures |= P.evaluate_gw(args, gw, vae_v, vae_attr, vae_ck, images, attrs, u_v, u_a, n_eval, silent)
    assert set(figures) == set(record["held_out"])
    for key, value in record["held_out"].items():
        assert figures[key] == pytest.approx(value, rel=1e-3, abs=1e-4), key
    assert figures["tr_image_to_class_accuracy"] > 0.95  # a usable GW, not just a reproducible one
    assert sum(p.stat().st_size for p in BUNDLE.iterdir()) < 10 * 2**20


def test_the_robodesk_bundle_reproduces_its_recorded_held_out_figures_and_carries_the_task():
    """The shipped float16 weights on the shipped held-out samples give the recorded figures, and the
    fused z recovers the end effector and the buttons (R^2 >= 0.9) from data without push_red / push_blue."""
    record = json.loads((ROBODESK.parent / "robodesk.json").read_text())
    figures = held_out_figures(ROBODESK, "robodesk")
    assert set(figures) == set(record["held_out"])
    for key, value in record["held_out"].items():
        if not math.isnan(value):  # a group constant over the held-out samples has no R^2
            assert figures[key] == pytest.approx(value, rel=1e-3, abs=1e-4), key
    for group in ("end_effector", "button_green"):
        assert figures[f"fused_{group}_r2"] >= 0.9, group
    assert figures["fused_end_effector_error_cm"] < 3.0  # an agent action moves it 1-4 cm
    vae, gw = (torch.load(ROBODESK / f, weights_only=False) for f in ("vae.pt", "gw.pt"))
    assert gw["vae_digest"] == G.vae_digest(vae)  # the GW records the VAE it was trained on
    assert record["render_quality"] == "fast"
    assert "expert/push_green" in record["data"]  # labels "source/task"
    assert not any("push_red" in k or "push_blue" in k for k in record["data"])  # zero-shot for the GW
    assert sum(p.stat().st_size for p in ROBODESK.iterdir()) < 25 * 2**20


def test_own_checkpoints_win_over_the_bundle_and_are_never_mixed_with_it(tmp_path, capsys):
    ck = tmp_path / "ck"
    paths = G.pretrained_paths(str(ck), "simple_shapes", {"vae.pt": None, "gw.pt": None})
    assert paths == {"vae.pt": BUNDLE / "vae.pt", "gw.pt": BUNDLE / "gw.pt"}
    assert "using the bundled copies" in capsys.readouterr().out
    (ck / "simple_shapes").mkdir(parents=True)
    (ck / "simple_shapes" / "vae.pt").write_bytes(b"")  # a VAE of one's own, no GW yet: no mixing
    paths = G.pretrained_paths(str(ck), "simple_shapes", {"vae.pt": None, "gw.pt": None})
    assert paths == {"vae.pt": ck / "simple_shapes" / "vae.pt", "gw.pt": ck / "simple_shapes" / "gw.pt"}
    given = G.pretrained_paths(str(ck), "simple_shapes", {"vae.pt": "mine.pt"})
    assert given == {"vae.pt": Path("mine.pt")}
    assert "bundled" not in capsys.readouterr().out
    rd = G.pretrained_paths(str(ck), "robodesk", {"vae.pt": None, "gw.pt": None})
    assert rd == {"vae.pt": ROBODESK / "vae.pt", "gw.pt": ROBODESK / "gw.pt"}


def test_a_fresh_clone_trains_on_the_bundle(tmp_path):
    out = run_cli("gw_dreamer.py", tmp_path, "--env", "simple_shapes", *AGENT_TINY["gw_dreamer.py"])
    assert out.returncode == 0, out.stdout + out.stderr
    first = out.stdout.splitlines()[0]
    assert first.startswith(
        "[pretrained] checkpoints/simple_shapes holds no vae.pt / gw.pt: using the bundled"
    )


@pytest.mark.parametrize("script", ["gw_dreamer.py", "dreamer_baseline.py"])
def test_a_missing_robodesk_gw_gives_the_whole_pipeline(tmp_path, script):
    """With a VAE path of one's own that does not exist, the bundle is not used and the message gives
    the command of the whole RoboDesk pipeline with the user's folder, and where the paper's scale is."""
    extra = ["--obs", "vae"] if script == "dreamer_baseline.py" else []
    mine = ["--checkpoint-dir", "mine", "--vae-checkpoint", "mine/robodesk/vae.pt"]
    out = run_cli(script, tmp_path, "--env", "robodesk", *mine, *extra)
    assert out.returncode == 2
    msg = out.stderr
    assert f"no vae checkpoint at {'mine/robodesk/vae.pt'}" in msg
    assert "`python pretrain_vae_gw.py --env robodesk --cpu-preset --checkpoint-dir mine`" in msg
    assert "min on 2 cores" in msg and "docs/pretrain_vae_gw.md" in msg


def test_a_missing_simple_shapes_vae_names_every_stage_and_the_folder(tmp_path):
    ck = tmp_path / "mine" / "simple_shapes"
    ck.mkdir(parents=True)
    (ck / "gw.pt").write_bytes(b"")  # a folder of one's own: the bundle is not used
    out = run_cli("gw_dreamer.py", tmp_path, "--env", "simple_shapes", "--checkpoint-dir", "mine")
    assert out.returncode == 2
    want = "pretrain_vae_gw.py --env simple_shapes --stages collect vae gw --cpu-preset --checkpoint-dir mine"
    assert want in out.stderr
