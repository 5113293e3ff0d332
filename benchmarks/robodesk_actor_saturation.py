"""How saturated a RoboDesk GW-Dreamer actor is: its Gaussian mean before the tanh on replayed states.

Under dynamics backpropagation the actor's mean m can grow until tanh(m) sits at the action bound, where
its gradient vanishes and the policy can no longer change (docs/gw_dreamer.md, "RoboDesk on a CPU").
For each agent checkpoint this prints, on the newest states of replayed sequences (the states dreams
start from): the median and 90th percentile of |m|, the share of means with |tanh(m)| > 0.99, the mean
action and std per dimension, and the share of the last 2,000 stored actions at a bound.

    python benchmarks/robodesk_actor_saturation.py \\
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
    return {
        "env_steps": ck["state"]["env_steps"],
        "loss_z": float(terms["loss_z"]),
        "m_median": float(m.abs().median()),
        "m_p90": float(m.abs().quantile(0.9)),
        "at_bound": float((mean.abs() > 0.99).float().mean()),
        "mean": mean.mean(0).numpy(),
        "std": std.mean(0).numpy(),
        "stored_at_bound": (np.abs(stored) >= 0.999).mean(0),
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
        out.append(r)
    return out


if __name__ == "__main__":
    main(tyro.cli(Args))
