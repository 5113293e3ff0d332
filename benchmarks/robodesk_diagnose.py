"""What a RoboDesk GW-Dreamer agent checkpoint has learnt, for runs that stall below the criterion.

1. Actor saturation. Under dynamics backpropagation the actor's mean m can grow until tanh(m) sits at the
   action bound, where its gradient vanishes and the policy can no longer change (docs/gw_dreamer.md,
   "RoboDesk on a CPU"). On the newest states of replayed sequences (the states dreams start from): the
   median and 90th percentile of |m|, the share of means with |tanh(m)| > 0.99, the mean action and std
   per dimension, and the share of the last 2,000 stored actions at a bound.
2. The world model's reward on the agent's own data: after 64 real steps of a replayed sequence, the
   next 20 rewards predicted one step ahead (real z read each step) and open loop (its own z fed back,
   as in a dream) with the actions that were taken, against the real rewards: mean |r_hat - r| at
   horizons 1, 5, 10 and 20, and the correlation of the 20-step sums.

    python benchmarks/robodesk_diagnose.py \\
        checkpoints/robodesk/agents/gw_dreamer_gw_robodesk_push_green_s1.pt
"""

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro
from tyro.conf import Positional

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import gw_dreamer as G  # noqa: E402


@dataclass
class Args:
    checkpoints: Positional[tuple[str, ...]]
    """gw_dreamer.py RoboDesk agent checkpoints"""
    sequences: int = 64
    """replayed sequences (of the run's --batch-length) whose newest states are read"""
    seed: int = 0
    """seed of the replay sampling"""


@torch.no_grad()
def saturation(path: str, sequences: int, seed: int) -> dict:
    ck = torch.load(path, weights_only=False, map_location="cpu")
    if ck.get("kind") != "gw_dreamer" or ck.get("env") != "robodesk":
        raise SystemExit(f"error: {path} is not a gw_dreamer.py RoboDesk agent checkpoint")
    args = G.Args(**{k: v for k, v in ck["args"].items() if k in G.Args.__dataclass_fields__}).resolve()
    z_dim = ck["replay"]["z"].shape[-1]
    agent = G.Agent("robodesk", z_dim, args.reward_loss, args.return_norm_decay, args.cpu_preset)
    agent.load_state_dict(ck["agent"])
    replay = G.Replay(args.buffer_size, args.num_envs, z_dim, G.SIZES["robodesk"]["actions"], seed)
    state = ck["replay"] | {"rng": np.random.default_rng(seed).bit_generator.state}
    replay.load_state_dict(state)
    batch = {k: torch.as_tensor(v) for k, v in replay.sample(sequences, args.batch_length).items()}
    _, terms, h_entry, _ = G.world_model_loss(agent.wm, agent.reward_dec, batch, args)
    m, s = agent.actor.net(h_entry[:, -1]).chunk(2, -1)
    mean, std = torch.tanh(m), 0.9 * torch.sigmoid(s + 2.0) + 0.1
    count = int(ck["replay"]["count"][0])
    stored = ck["replay"]["a"][0][:count][-2000:]
    out = open_loop_rewards(agent, ck["replay"], seed)
    return out | {
        "env_steps": ck["state"]["env_steps"],
        "loss_z": float(terms["loss_z"]),
        "m_median": float(m.abs().median()),
        "m_p90": float(m.abs().quantile(0.9)),
        "at_bound": float((mean.abs() > 0.99).float().mean()),
        "mean": mean.mean(0).numpy(),
        "std": std.mean(0).numpy(),
        "stored_at_bound": (np.abs(stored) >= 0.999).mean(0),
    }


@torch.no_grad()
def open_loop_rewards(
    agent, replay: dict, seed: int, warm: int = 64, horizon: int = 20, n: int = 256
) -> dict:
    """Predicted against real rewards over ``horizon`` steps after ``warm`` real ones, in the newest
    30,000 entries of the first replay stream (sequences that cross an episode start are left out)."""
    count = int(replay["count"][0])
    z, a, r, first = (torch.as_tensor(replay[k][0][:count]) for k in ("z", "a", "r", "first"))
    lo = max(0, count - 30_000)
    starts = np.random.default_rng(seed).integers(lo, count - warm - horizon - 1, n)
    s0 = torch.as_tensor([s for s in starts if not first[s + 1 : s + warm + horizon + 1].any()])
    h = torch.zeros(len(s0), agent.wm.hidden)
    for t in range(warm):
        h = agent.wm.step(h, z[s0 + t], a[s0 + t])
    h_one, h_open, z_open, one, open_, real = h, h, z[s0 + warm], [], [], []
    for k in range(horizon):
        t = s0 + warm + k
        h_one = agent.wm.step(h_one, z[t], a[t])
        one.append(agent.reward_dec.value(agent.wm.heads(h_one)[1]))
        h_open = agent.wm.step(h_open, z_open, a[t])
        z_open, r_out, _ = agent.wm.heads(h_open)
        open_.append(agent.reward_dec.value(r_out))
        real.append(r[t])
    one, open_, real = (torch.stack(x).numpy() for x in (one, open_, real))
    at = [0, 4, 9, horizon - 1]
    return {
        "sequences": len(s0),
        "reward_mean": float(real.mean()),
        "one_step_err": np.abs(one - real).mean(1)[at],
        "open_loop_err": np.abs(open_ - real).mean(1)[at],
        "return_corr": float(np.corrcoef(open_.sum(0), real.sum(0))[0, 1]),
    }


def main(args: Args) -> list[dict]:
    torch.set_num_threads(1)
    out = []
    for path in args.checkpoints:
        r = saturation(path, args.sequences, args.seed)
        print(
            f"{path} (frame {r['env_steps']:,}): |m| median {r['m_median']:.2f}, 90% {r['m_p90']:.2f}; "
            f"{100 * r['at_bound']:.0f}% of the means at the bound; mean {np.round(r['mean'], 2)}, "
            f"std {np.round(r['std'], 3)}; stored actions at a bound {np.round(r['stored_at_bound'], 2)}; "
            f"world-model z loss {r['loss_z']:.3f}"
        )
        print(
            f"  rewards ({r['sequences']} sequences, real mean {r['reward_mean']:.2f} per agent step): "
            f"|r_hat - r| at horizons 1/5/10/20 one step ahead {np.round(r['one_step_err'], 3)}, open loop "
            f"{np.round(r['open_loop_err'], 3)}; 20-step sums correlate {r['return_corr']:.3f} (open loop)"
        )
        out.append(r)
    return out


if __name__ == "__main__":
    main(tyro.cli(Args))
