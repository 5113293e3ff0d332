"""Our DreamerV3 update (dreamer_baseline.py) beside SheepRL's (sheeprl 0.8.4) at the same model size and
batch, timed in one run on the same machine: seconds per update of each, the ratio, and the parameter
counts. Both get random weights and a random replayed batch of the same shape; speed does not depend on
them.

sheeprl is an optional dependency, not in requirements.txt nor in CI; it installs beside torch 2.13's CPU
build in a virtual environment of its own:

    python -m venv peer && peer/bin/pip install torch==2.13.0 sheeprl==0.8.4 tyro
    peer/bin/python benchmarks/peer_dreamerv3.py                      # Simple Shapes, Dreamer 2M
    peer/bin/python benchmarks/peer_dreamerv3.py --setting robodesk:12m

The sizes are dreamer_baseline.py's (--size): GRU units, RSSM hidden size, dense units and layers, CNN
channel multiplier, 32 latents of `classes` classes; SheepRL's architecture (LayerNorm, SiLU, its CNN
and its heads) then gives its own parameter count, printed next to ours. One update is the world model on
batch x length replayed steps, then imagination (horizon 15) from every replayed state and the actor and
critic updates, in both.
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import dreamer_baseline as D  # noqa: E402


@dataclass
class Args:
    setting: str = "simple_shapes:2m"
    """env:size of dreamer_baseline.py"""
    batch_size: int = 16
    """replayed sequences per update (the paper's 16)"""
    batch_length: int = 64
    """steps per sequence (the paper's 65 for ours; 64 for both here, SheepRL's usual length)"""
    updates: int = 3
    """timed updates of each, in turn, after one warm-up update (medians are printed)"""
    threads: int = 0
    """torch CPU threads (0: torch's default)"""
    keep_freed_memory: bool = True
    """the allocator setting every script of this project applies at start (``keep_freed_memory``: large
    freed blocks stay in the heap), here for both updates; --no-keep-freed-memory times both with glibc's
    default, which page-faults large tensors in afresh on every update"""
    match_parameters: bool = True
    """give SheepRL's model the recurrent state size (a multiple of 64) whose trainable parameters come
    closest to ours (its GRU is dense, ours DreamerV3's block-diagonal one, so the same sizes give it more
    weights); --no-match-parameters keeps our sizes as they are"""


def ours(env: str, size: str, a: Args):
    """(one update, trainable parameters) of dreamer_baseline.py."""
    args = D.Args(env=env, size=size, batch_size=a.batch_size, batch_length=a.batch_length).resolve()
    spaces = D.Observer(env, "raw", None).spaces(env)
    agent = D.Agent(env, spaces, args)
    opts = D.make_optimizers(agent, args)
    replay = D.Replay(4 * a.batch_length, 1, spaces, agent.n_actions, 0)
    rng = np.random.default_rng(0)
    for t in range(4 * a.batch_length):
        entry = {"image": rng.integers(0, 256, (1, *spaces["image"])).astype(np.uint8)}
        entry |= {
            "attr": rng.normal(size=(1, *spaces["attr"])),
            "action": np.eye(agent.n_actions)[[t % agent.n_actions]],
        }
        entry |= {"reward": [-1.0], "terminal": [0.0], "first": [float(t == 0)]}
        replay.add(np.array([0]), entry)
    return (lambda: D.train_update(agent, opts, replay, args)), agent.n_trainable()["total"], args


def theirs(env: str, args: D.Args, a: Args, deter: int | None = None, build_only: bool = False):
    """(one update, trainable parameters) of SheepRL's DreamerV3 at the sizes of ``args`` (its recurrent
    state ``deter`` if given)."""
    import gymnasium as gym
    import hydra
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf
    from sheeprl.algos.dreamer_v3 import dreamer_v3 as S
    from sheeprl.algos.dreamer_v3.agent import build_agent
    from sheeprl.algos.dreamer_v3.utils import Moments
    from sheeprl.utils.utils import dotdict

    spec = D.ENV_SPECS[env]
    overrides = [
        "exp=dreamer_v3",
        "env=dummy",
        f"env.screen_size={spec['image']}",
        "algo.cnn_keys.encoder=[rgb]",
        "algo.mlp_keys.encoder=[state]",
        f"algo.per_rank_batch_size={a.batch_size}",
        f"algo.per_rank_sequence_length={a.batch_length}",
        f"algo.horizon={args.imag_horizon}",
        f"algo.dense_units={args.units}",
        f"algo.mlp_layers={args.layers}",
        f"algo.world_model.discrete_size={args.classes}",
        f"algo.world_model.stochastic_size={D.STOCH}",
        f"algo.world_model.encoder.cnn_channels_multiplier={args.cnn_depth}",
        f"algo.world_model.recurrent_model.recurrent_state_size={deter or args.deter}",
        f"algo.world_model.transition_model.hidden_size={args.hidden}",
        f"algo.world_model.representation_model.hidden_size={args.hidden}",
        "fabric.accelerator=cpu",
        "metric.log_level=0",
    ]
    with initialize_config_module("sheeprl.configs", version_base="1.3"):
        cfg = dotdict(
            OmegaConf.to_container(compose(config_name="config", overrides=overrides), resolve=True)
        )
    fabric = hydra.utils.instantiate(cfg.fabric, callbacks=[], _convert_="all")
    obs_space = gym.spaces.Dict(
        {
            "rgb": gym.spaces.Box(0, 255, (3, spec["image"], spec["image"]), np.uint8),
            "state": gym.spaces.Box(-np.inf, np.inf, (spec["attr"],), np.float32),
        }
    )
    n_act, continuous = spec["actions"], env == "robodesk"
    actions_dim = (n_act,) if continuous else [n_act]
    world_model, actor, critic, target_critic, _ = build_agent(
        fabric, actions_dim, continuous, cfg, obs_space
    )
    n = sum(p.numel() for mod in (world_model, actor, critic) for p in mod.parameters() if p.requires_grad)
    if build_only:
        return None, n
    opt = [
        hydra.utils.instantiate(c.optimizer, params=m.parameters(), _convert_="all")
        for c, m in ((cfg.algo.world_model, world_model), (cfg.algo.actor, actor), (cfg.algo.critic, critic))
    ]
    opt = fabric.setup_optimizers(*opt)
    m = cfg.algo.actor.moments
    moments = Moments(m.decay, m.max, m.percentile.low, m.percentile.high)
    T, B = a.batch_length, a.batch_size
    g = torch.Generator().manual_seed(0)
    data = {
        "rgb": torch.randint(0, 256, (T, B, 3, spec["image"], spec["image"]), generator=g).float(),
        "state": torch.randn(T, B, spec["attr"], generator=g),
        "actions": torch.nn.functional.one_hot(torch.randint(0, n_act, (T, B), generator=g), n_act).float(),
        "rewards": -torch.ones(T, B, 1),
        "terminated": torch.zeros(T, B, 1),
        "truncated": torch.zeros(T, B, 1),
        "is_first": torch.zeros(T, B, 1),
    }

    def update():
        batch = {k: v.clone() for k, v in data.items()}
        S.train(
            fabric,
            world_model,
            actor,
            critic,
            target_critic,
            *opt,
            batch,
            None,
            cfg,
            continuous,
            actions_dim,
            moments,
        )

    return update, n


def timed(fns: list, n: int) -> list[tuple[float, float]]:
    """(wall seconds, CPU seconds of this process) per call of each of ``fns``, medians of ``n`` calls
    taken in turn, after one warm-up call each. Taking turns spreads a busy machine's slow spells over
    both; the CPU time does not count the time the process waited for a core."""
    for fn in fns:
        fn()
    times = [[] for _ in fns]
    for _ in range(n):
        for fn, out in zip(fns, times, strict=True):
            wall, cpu = time.perf_counter(), time.process_time()
            fn()
            out.append((time.perf_counter() - wall, time.process_time() - cpu))
    return [tuple(float(np.median(col)) for col in zip(*out, strict=True)) for out in times]


if __name__ == "__main__":
    a = tyro.cli(Args)
    if a.threads:
        torch.set_num_threads(a.threads)
    if a.keep_freed_memory:
        D.keep_freed_memory()
    env, size = a.setting.split(":")
    torch.manual_seed(0)
    our_update, our_n, args = ours(env, size, a)
    deter = args.deter
    if a.match_parameters:  # the recurrent state size whose parameter count is closest to ours
        sizes = range(64, 2 * args.deter + 1, 64)
        deter = min(sizes, key=lambda d: abs(theirs(env, args, a, d, build_only=True)[1] - our_n))
    their_update, their_n = theirs(env, args, a, deter)
    import sheeprl

    allocator = "large freed blocks kept (keep_freed_memory)" if a.keep_freed_memory else "glibc's default"
    print(f"torch {torch.__version__}, sheeprl {sheeprl.__version__}, {torch.get_num_threads()} threads, CPU")
    print(f"{env} {size}: batch {a.batch_size} x {a.batch_length}, horizon {args.imag_horizon}")
    print(f"allocator: {allocator}")
    print(f"recurrent state: ours {args.deter} (8 blocks), SheepRL's {deter} (dense)")
    ours_f, theirs_f = D.count_flops(our_update)[1], D.count_flops(their_update)[1]
    (ours_s, ours_cpu), (theirs_s, theirs_cpu) = timed([our_update, their_update], a.updates)
    rows = (
        ("ours (dreamer_baseline.py)", ours_s, ours_cpu, ours_f, our_n),
        ("SheepRL's DreamerV3", theirs_s, theirs_cpu, theirs_f, their_n),
    )
    for name, sec, cpu, flops, n in rows:
        rate = f"{flops / 1e9:7.1f} GFLOP ({flops / 1e9 / cpu:5.1f} GFLOP per CPU s)"
        print(f"{name:27s} {sec:7.3f} s per update ({cpu:7.3f} CPU s), {rate}, {n:,} trainable parameters")
    print(
        f"ratio (their time / ours): {theirs_s / ours_s:.2f}x per update, "
        f"{theirs_cpu / ours_cpu:.2f}x in CPU time, "
        f"{(theirs_cpu / theirs_f) / (ours_cpu / ours_f):.2f}x per FLOP (CPU time)"
    )
