"""pretrain_vae_gw.py: stages through the CLI, GW losses by hand, learning, reloading, errors."""

import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn as nn
from conftest import run_pretrain
from torch.utils.tensorboard import SummaryWriter

import pretrain_vae_gw as P


@pytest.fixture
def trained(pretrained):
    return pretrained


def test_all_stages_run_through_the_cli(trained, tmp_path):
    tmp, log, log_clip = trained
    assert len(P.shard_paths(tmp / "data" / "simple_shapes")) == 2
    for name, kind in (("vae", "vae"), ("gw", "gw"), ("clip", "gw")):
        ck = torch.load(tmp / "ck" / "simple_shapes" / f"{name}.pt", weights_only=False)
        assert ck["kind"] == kind and ck["env"] == "simple_shapes"
    assert (
        "held-out evaluation" in log
        and "tr_image_to_class_accuracy" in log
        and "fusion_to_rotation_error_rad" in log
    )
    assert "[clip]" in log_clip
    assert P.label_counts(tmp / "data" / "simple_shapes") == {"random/": 600}
    assert "fusion_to_position_error_px_outside" not in log  # no sample past the dataset's range
    assert list((tmp / "runs").iterdir())  # TensorBoard logs under runs/
    # Collecting again appends nothing once enough samples exist; asking for more appends a shard (on a
    # copy: the session's data must stay what its checkpoints were made from).
    shutil.copytree(tmp / "data", tmp_path / "data")
    assert "already holds 600" in run_pretrain(tmp_path, "--env", "simple_shapes", "--stages", "collect")
    run_pretrain(tmp_path, "--env", "simple_shapes", "--stages", "collect", "--n-samples", "700")
    images, attrs = P.load_data(tmp_path / "data" / "simple_shapes", "simple_shapes")
    assert images.shape == (700, 32, 32, 3) and attrs.shape == (700, 11)


def test_robodesk_stages_on_tiny_data(pretrained_robodesk):
    tmp, log = pretrained_robodesk
    assert "RoboDesk data: 20 expert (push_green), 20 random (push_green)" in log
    ck = torch.load(tmp / "ck" / "robodesk" / "gw.pt", weights_only=False)
    assert ck["config"]["z"] == 76 and ck["gw"]["e.v.0.weight"].shape == (512, 40)


def test_checkpoints_reload_to_identical_outputs(trained):
    tmp = trained[0]
    ck_dir = tmp / "ck" / "simple_shapes"
    vae_v, vae_attr, vae_ck = P.load_vaes(ck_dir / "vae.pt", "simple_shapes")
    again_v, again_attr, _ = P.load_vaes(ck_dir / "vae.pt", "simple_shapes")
    images, attrs = P.load_data(tmp / "data" / "simple_shapes", "simple_shapes")
    x = P.images_to_tensor(images[:16], "cpu")
    torch.testing.assert_close(vae_v.encode(x)[0], again_v.encode(x)[0], rtol=0, atol=0)
    gw_ck = P.load_checkpoint(ck_dir / "gw.pt", "gw", "simple_shapes", "make it")
    spec = P.ENV_SPECS["simple_shapes"]
    gw = P.GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"])
    gw.load_state_dict(gw_ck["gw"])
    u_v, u_a = vae_v.encode(x)[0], vae_attr.encode(torch.as_tensor(attrs[:16]))[0]
    z = gw.fuse(u_v, u_a, 0.5, 0.5)
    gw2 = P.GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"])
    gw2.load_state_dict(torch.load(ck_dir / "gw.pt", weights_only=False)["gw"])
    torch.testing.assert_close(gw2.fuse(u_v, u_a, 0.5, 0.5), z, rtol=0, atol=0)


def test_mismatched_or_missing_checkpoints_and_bad_data_are_explained(trained, tmp_path):
    ck = trained[0] / "ck" / "simple_shapes" / "vae.pt"
    with pytest.raises(ValueError, match="made for env 'simple_shapes'.*'robodesk'.*--env robodesk"):
        P.load_vaes(ck, "robodesk")
    with pytest.raises(ValueError, match="'vae' checkpoint, expected 'gw'"):
        P.load_checkpoint(ck, "gw", "simple_shapes", "cmd")
    with pytest.raises(P.UsageError, match="--stages collect vae"):
        P.load_vaes(tmp_path / "nothing.pt", "simple_shapes")
    with pytest.raises(P.UsageError, match="--stages collect"):
        P.load_data(tmp_path, "simple_shapes")
    P.write_shard(tmp_path, np.zeros((4, 64, 64, 3), np.uint8), np.zeros((4, 11)), "random")
    with pytest.raises(ValueError, match="do not match env simple_shapes"):
        P.load_data(tmp_path, "simple_shapes")


class Scale(nn.Module):
    def __init__(self, s):
        super().__init__()
        self.s = s

    def forward(self, x):
        return self.s * x


def hand_gw():
    """A GW whose encoders and decoders are fixed scalings, so every loss term is computable by hand."""
    gw = P.GlobalWorkspace(2, 2, 4)
    gw.e = nn.ModuleDict({"v": Scale(1.0), "attr": Scale(2.0)})
    gw.d = nn.ModuleDict({"v": Scale(1.0), "attr": Scale(0.5)})
    return gw


def test_gw_losses_match_hand_computed_values():
    u = {"v": torch.tensor([[0.5, -1.0]]), "attr": torch.tensor([[0.2, 0.4]])}
    t = np.tanh
    uv, ua = np.array([0.5, -1.0]), np.array([0.2, 0.4])
    dcy = (np.mean((t(uv) - uv) ** 2) + np.mean((0.5 * t(2 * ua) - ua) ** 2)) / 2
    tr = (np.mean((0.5 * t(uv) - ua) ** 2) + np.mean((t(2 * ua) - uv) ** 2)) / 2
    cy = (np.mean((t(2 * 0.5 * t(uv)) - uv) ** 2) + np.mean((0.5 * t(t(2 * ua)) - ua) ** 2)) / 2
    for alpha in (1.0, 0.0, 0.5):
        fused = t(alpha * uv + (1 - alpha) * 2 * ua)
        fusion = (np.mean((fused - uv) ** 2) + np.mean((0.5 * fused - ua) ** 2)) / 2
        terms = P.gw_losses(hand_gw(), u, torch.tensor([[alpha]]), 0.07)
        assert terms["dcy"].item() == pytest.approx(dcy)
        assert terms["tr"].item() == pytest.approx(tr)
        assert terms["cy"].item() == pytest.approx(cy)
        assert terms["fusion"].item() == pytest.approx(fusion)
    # alpha_v = 1 fusion is the vision demi-cycle and translation; alpha_v = 0 the attribute ones.
    gw = hand_gw()
    z1 = gw.fuse(u["v"], u["attr"], 1.0, 0.0)
    torch.testing.assert_close(z1, torch.tanh(u["v"]))
    # Contrastive: two samples, logits = cos similarity / T, symmetric cross-entropy.
    u2 = {"v": torch.tensor([[1.0, 0.0], [0.0, 1.0]]), "attr": torch.tensor([[1.0, 0.0], [1.0, 1.0]])}
    c = 1 / np.sqrt(2)
    logits = np.array([[1.0, c], [0.0, c]]) / 0.07
    rows = -np.mean([logits[i, i] - np.log(np.exp(logits[i]).sum()) for i in range(2)])
    cols = -np.mean([logits[i, i] - np.log(np.exp(logits[:, i]).sum()) for i in range(2)])
    cont = P.gw_losses(hand_gw(), u2, torch.full((2, 1), 0.5), 0.07)["cont"].item()
    assert cont == pytest.approx((rows + cols) / 2, rel=1e-5)


def test_clip_preset_has_zero_broadcast_gradients():
    torch.manual_seed(0)
    gw = P.GlobalWorkspace(10, 10, 64)
    u = {"v": torch.randn(32, 10), "attr": torch.randn(32, 10)}
    terms = P.gw_losses(gw, u, torch.rand(32, 1), 0.07)
    betas = P.PRESETS["clip"]
    sum(betas[k] * terms[k] for k in terms).backward()
    for p in gw.d.parameters():
        assert p.grad is None or torch.count_nonzero(p.grad) == 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in gw.e.parameters())


def test_losses_fall_on_a_fixed_batch():
    torch.manual_seed(0)
    from envs.simple_shapes import sample_dataset

    d = sample_dataset(32, seed=0)
    vae_v, vae_attr = P.make_vaes("simple_shapes", 32)
    x, a = P.images_to_tensor(d["image"], "cpu"), torch.as_tensor(d["attr"])
    opt = torch.optim.Adam([*vae_v.parameters(), *vae_attr.parameters()], lr=2e-3)
    first = None
    for _ in range(40):
        loss = vae_v.loss(x, 0.1)[0] + vae_attr.loss(a, 0.05)[0]
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first
    gw = P.GlobalWorkspace(10, 10, 64)
    u = {"v": torch.randn(64, 10), "attr": torch.randn(64, 10)}
    opt = torch.optim.Adam(gw.parameters(), lr=3e-3)
    alpha = torch.rand(64, 1)
    losses = []
    for _ in range(150):
        terms = P.gw_losses(gw, u, alpha, 0.07)
        loss = sum(P.PRESETS["gw"][k] * terms[k] for k in terms)
        losses.append(loss.item())
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert losses[-1] < 0.6 * losses[0]


def test_vae_and_gw_stages_resume_after_an_interruption(tmp_path, monkeypatch, capsys):
    from envs.simple_shapes import sample_dataset

    d = sample_dataset(200, seed=0)
    P.write_shard(tmp_path / "data" / "simple_shapes", d["image"], d["attr"], "random")
    tiny = dict(vae_steps=12, vae_batch_size=8, vae_width=32, save_every=5, log_every=100, eval_size=20)
    args = P.Args(data_dir=str(tmp_path / "data"), checkpoint_dir=str(tmp_path / "ck"), **tiny).resolve()
    real_save = P.atomic_save

    def interrupted(obj, path):  # the run dies when it writes its final checkpoint
        if "kind" in obj:
            raise KeyboardInterrupt
        real_save(obj, path)

    monkeypatch.setattr(P, "atomic_save", interrupted)
    writer, no_stop = SummaryWriter(str(tmp_path / "runs")), SimpleNamespace(requested=False)
    with pytest.raises(KeyboardInterrupt):
        P.train_vae(args, writer, no_stop)
    partial = tmp_path / "ck" / "simple_shapes" / "vae.partial.pt"
    assert torch.load(partial, weights_only=False)["step"] == 10
    monkeypatch.setattr(P, "atomic_save", real_save)
    P.train_vae(args, writer, no_stop)
    assert "continuing the unfinished stage in" in capsys.readouterr().out
    assert not partial.exists() and (tmp_path / "ck" / "simple_shapes" / "vae.pt").is_file()
    # The gw stage resumes the same way.
    args.gw_steps, args.gw_batch_size = 12, 16
    monkeypatch.setattr(P, "atomic_save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        P.train_gw(args, writer, no_stop)
    monkeypatch.setattr(P, "atomic_save", real_save)
    P.train_gw(args, writer, no_stop)
    assert "from step 10" in capsys.readouterr().out
    assert (tmp_path / "ck" / "simple_shapes" / "gw.pt").is_file()


def test_defaults_follow_the_tables_and_the_cpu_preset_is_small():
    ss, rd = P.Args(env="simple_shapes").resolve(), P.Args(env="robodesk").resolve()
    assert (ss.n_samples, ss.vae_batch_size, ss.vae_steps, ss.vae_width) == (500_000, 2056, 500_000, 1024)
    ss_rates = (ss.vae_lr_v, ss.vae_lr_start_end, ss.gw_lr, ss.gw_lr_start_end, ss.gw_weight_decay)
    assert ss_rates == (5e-3, 5e-3, 5e-3, 5e-4, 1e-5)
    rd_rates = (rd.vae_lr_v, rd.vae_lr_attr, rd.gw_lr, rd.gw_lr_start_end, rd.gw_weight_decay)
    assert rd_rates == (3e-4, 5e-4, 3e-4, 1e-4, 1e-6)
    cpu = P.Args(env="simple_shapes", cpu_preset=True).resolve()
    assert (cpu.n_samples, cpu.vae_width, cpu.vae_steps, cpu.vae_batch_size, cpu.gw_steps) == (
        60_000,
        64,
        5_000,
        128,
        20_000,
    )
    assert (cpu.beta_attr, cpu.attr_updates_per_step) == (0.005, 4)
    # One-cycle schedule: starts and ends at the start/end rate, peaks at the max rate.
    opt = torch.optim.AdamW([torch.zeros(1, requires_grad=True)])
    sched = P.one_cycle(opt, 5e-3, 5e-4, 100)
    lrs = []
    for _ in range(100):
        lrs.append(sched.get_last_lr()[0])
        opt.step()
        sched.step()
    assert (
        lrs[0] == pytest.approx(5e-4)
        and max(lrs) == pytest.approx(5e-3)
        and lrs[-1] == pytest.approx(5e-4, rel=0.05)
    )


def test_wide_share_through_the_cli(tmp_path):
    """--wide-share 0.25: the shards label the samples drawn at wide positions, and the evaluation reports
    how well fused z keeps their position apart."""
    log = run_pretrain(tmp_path, "--env", "simple_shapes", "--wide-share", "0.25")
    counts = P.label_counts(tmp_path / "data" / "simple_shapes")
    assert set(counts) == {"random/", "random_wide/"} and 100 < counts["random_wide/"] < 200, counts
    assert "fusion_to_position_error_px_outside" in log


def test_wide_share_is_checked():
    with pytest.raises(ValueError, match="--wide-share"):
        P.Args(env="robodesk", wide_share=0.25).resolve()
    with pytest.raises(ValueError, match="--wide-share"):
        P.Args(wide_share=1.5).resolve()


def test_flags_given_explicitly_override_the_cpu_preset():
    args = P.Args(cpu_preset=True, vae_width=128, vae_steps=2_400).resolve()
    assert (args.vae_width, args.vae_steps, args.vae_batch_size) == (128, 2_400, 128)


def test_two_collecting_workers_give_the_simple_shapes_data_of_one(tmp_path):
    """Simple Shapes shards drawn by two processes are those one process draws (one seed per shard)."""
    for workers in ("1", "2"):
        (tmp_path / workers).mkdir()
        flags = "--env simple_shapes --stages collect --n-samples 700 --shard-size 300 --workers"
        run_pretrain(tmp_path / workers, *flags.split(), workers)
    one, two = (P.shard_paths(tmp_path / w / "data" / "simple_shapes") for w in ("1", "2"))
    assert [len(np.load(p)["attr"]) for p in one] == [300, 300, 100]
    for a, b in zip(one, two, strict=True):
        with np.load(a) as x, np.load(b) as y:
            for key in ("image", "attr", "source"):
                np.testing.assert_array_equal(x[key], y[key], err_msg=key)


def test_robodesk_readout_figures_per_group_against_hand_computed_values():
    """Fails if R^2 is computed against the wrong mean or over the wrong columns, or the error is not
    in cm."""
    rng = np.random.default_rng(0)
    true = rng.normal(0, 0.1, (50, 76)).astype(np.float32)
    true[:, P.READOUT_GROUPS["drawer"]] = -0.1  # a drawer that never moved: no R^2
    exact = P.robodesk_readout(true.copy(), true, "fused")
    assert exact["fused_end_effector_r2"] == pytest.approx(1.0)
    assert exact["fused_end_effector_error_cm"] == pytest.approx(0.0, abs=1e-6)
    assert np.isnan(exact["fused_drawer_r2"])
    mean = np.broadcast_to(true.mean(0), true.shape).copy()  # predicting the mean: R^2 = 0 everywhere
    at_mean = P.robodesk_readout(mean, true, "vision")
    for group in ("end_effector", "gripper", "button_green", "ball", "flat_block"):
        assert at_mean[f"vision_{group}_r2"] == pytest.approx(0.0, abs=1e-6), group
    shifted = true.copy()
    shifted[:, 18:21] += 0.01  # 1 cm along each axis: sqrt(3) cm away
    ee = P.robodesk_readout(shifted, true, "attr")
    assert ee["attr_end_effector_error_cm"] == pytest.approx(100 * np.sqrt(3) * 0.01, rel=1e-4)
    y = true[:, 18:21].astype(np.float64)
    want = np.mean(1 - 50 * 0.01**2 / ((y - y.mean(0)) ** 2).sum(0))
    assert ee["attr_end_effector_r2"] == pytest.approx(want, rel=1e-4)
    assert ee["attr_ball_r2"] == pytest.approx(1.0)  # other groups untouched


def test_robodesk_cpu_preset_leaves_push_red_and_blue_out_and_uses_fast_images():
    args = P.Args(env="robodesk", cpu_preset=True).resolve()
    assert "push_red" not in args.tasks and "push_blue" not in args.tasks and "push_green" in args.tasks
    assert args.render_quality == "fast" and args.workers == 2
    paper = P.Args(env="robodesk").resolve()
    assert (paper.vae_width, paper.vae_steps, paper.n_samples, paper.tasks) == (1024, 500_000, 2_000_000, ())
    given = P.Args(env="robodesk", cpu_preset=True, tasks=("open_slide",), vae_steps=10).resolve()
    assert given.tasks == ("open_slide",) and given.vae_steps == 10  # explicit flags win


def test_robodesk_collection_interleaves_the_sources():
    """The held-out samples at the front of the data hold every source: fails if the episodes are
    written block by block, or an episode loses its own seed."""
    blocks = [("expert", "push_green", 8), ("expert", "open_slide", 6), ("random", "push_green", 8)]
    jobs = P.robodesk_jobs(blocks, seed=3, steps=4)
    assert [(src, task, n) for src, task, n, _ in jobs] == [
        ("expert", "push_green", 4),
        ("expert", "open_slide", 4),
        ("random", "push_green", 4),
        ("expert", "push_green", 4),
        ("expert", "open_slide", 2),
        ("random", "push_green", 4),
    ]
    assert jobs[4][3] == P.episode_seed(3, 1, 1) and jobs[3][3] == P.episode_seed(3, 0, 1)


def test_robodesk_attribute_scale_floors_still_dimensions_and_widens_spiking_ones():
    """A dimension still most of the time that spikes on contact (an object's velocity) is scaled so
    that 99.9% of its samples lie within +-3; a spread one keeps its std; a constant one the floor; the
    end effector's position is in 2 cm units whatever its spread (fails if it is scaled by its std)."""
    rng = np.random.default_rng(0)
    n = 100_000
    attr = np.zeros((n, 76), np.float32)
    attr[:, 0] = rng.uniform(-1, 1, n)  # spread: std 0.577, 99.9% within 1.73 std
    attr[: n // 100, 1] = 5.0 * rng.choice([-1, 1], n // 100)  # 1% spikes of +-5: std 0.5, spikes 10 std
    attr[:, 2] = 2e-5 * rng.standard_normal(n)  # a button nobody pressed
    mean, scale = P.normaliser(attr, "robodesk")
    assert scale[0] == pytest.approx(attr[:, 0].std(), rel=1e-4)
    assert scale[1] == pytest.approx(5.0 / 3, rel=1e-3)  # widened from 0.5
    assert scale[2] == P.ATTR_STD_FLOOR
    assert np.abs((attr[:, 1] - mean[1]) / scale[1]).max() <= 3.001
    attr[:, 18:21] = rng.uniform(-0.3, 0.3, (n, 3))  # the end effector, std 17 cm
    assert (P.normaliser(attr, "robodesk")[1][18:21] == np.float32(0.02)).all()
    zeros, ones = P.normaliser(attr[:, :11], "simple_shapes")
    assert not zeros.any() and (ones == 1).all()


def test_fusion_weights_are_a_tempered_softmax_of_uniform_noise():
    """alpha_v = exp(u_v / T) / (exp(u_v / T) + exp(u_attr / T)) = sigmoid((u_v - u_attr) / T) for the
    same uniform draws. Fails if the temperature multiplies instead of dividing, or alpha_attr is returned."""
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    alpha = P.fusion_weights(1000, 0.2, g1, "cpu")
    u = torch.rand(1000, 2, generator=g2)
    assert torch.allclose(alpha[:, 0], torch.sigmoid((u[:, 0] - u[:, 1]) / 0.2), atol=1e-6)
    assert alpha.shape == (1000, 1) and 0 < alpha.min() and alpha.max() < 1
    # a low temperature pushes the weights towards 0 or 1: at T = 0.2 a third lie beyond 0.9 / 0.1
    assert 0.25 < ((alpha > 0.9) | (alpha < 0.1)).float().mean() < 0.45
