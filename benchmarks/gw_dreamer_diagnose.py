"""What a Simple Shapes GW-Dreamer agent checkpoint has learnt, for runs that stall below the criterion:

1. the actions the policy took, as shares of the replayed transitions in windows of env steps;
2. the world model's one-step reward error (|r_hat - r| per step), on the replayed sequences with the
   actions taken, and on fresh episodes driven by random actions, for each of the 7 actions, with the share
   of states where the action the world model rates best is the truly best one (one-step reward);
3. greedy-policy episodes: return, normalised return and the share of rotation actions;
4. how far one action moves z (squared distance summed over z's dimensions, from states drawn as the
   env resets them) beside the world model's one-step z error on the replayed sequences (same measure:
   the z term of its loss);
5. how well the reward can be read from the true next z at all: an MLP of the reward head's depth fitted
   to the replayed (z_{t+1}, r_{t+1}) pairs, its mean error on held-out pairs;
6. the actor-critic's view: dreams of 20 steps from 2,048 replayed states, their lambda-returns, the
   return scale, and the advantages (R - v) overall and for each action the actor sampled.

    python benchmarks/gw_dreamer_diagnose.py \
        checkpoints/simple_shapes/agents/gw_dreamer_gw_simple_shapes_s1.pt

The VAE and GW checkpoints must be those the agent was trained on (the fingerprint is checked).
"""

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path[:0] = [
    str(Path(__file__).resolve().parents[1]),
    str(Path(__file__).resolve().parent / "experiments"),
]
import gw_dreamer_experiments as X  # noqa: E402

import gw_dreamer as G  # noqa: E402
from envs.simple_shapes import ACTION_DELTAS, N_ACTIONS, SimpleShapesVectorEnv, reward_and_goal  # noqa: E402


@dataclass
class Args:
    checkpoint: tyro.conf.Positional[str]
    """agent checkpoint written by gw_dreamer.py --env simple_shapes"""
    vae_checkpoint: str = "checkpoints/simple_shapes/vae.pt"
    """the frozen VAEs the agent was trained on"""
    gw_checkpoint: str = "checkpoints/simple_shapes/gw.pt"
    """the frozen GW the agent was trained on"""
    windows: tuple[int, ...] = (0, 1_000, 3_000, 6_000, 12_000, 20_000)
    """edges of the env-step windows for the action shares"""
    episodes: int = 20
    """fresh random-action episodes (and greedy-policy episodes)"""
    steps: int = 60
    """steps per random-action episode"""
    seed: int = 0
    """seed of the episodes, the dreams' action samples and the fitted reward head"""


@torch.no_grad()
def replay_errors(agent: G.Agent, replay: G.Replay, batches: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """|r_hat - r| and ||z_hat - z||^2 of the world model run over replayed sequences, as in its loss."""
    errs, z_errs = [], []
    for _ in range(batches):
        b = {k: torch.as_tensor(v) for k, v in replay.sample(64, 32).items()}
        h_before = G.world_model_loss(agent.wm, agent.reward_dec, b, G.Args())[2][:, :-1]  # h_t of each t
        z, a = b["z"][:, :-1], b["a"][:, :-1]
        h_next = agent.wm.step(h_before.flatten(0, 1), z.flatten(0, 1), a.flatten(0, 1))  # GRUCell: 2-D
        z_hat, r_out, _ = agent.wm.heads(h_next.view(*h_before.shape))
        keep = b["last"][:, :-1] == 0
        errs.append((agent.reward_dec.value(r_out) - b["r"][:, :-1])[keep].abs().numpy())
        z_errs.append(((z_hat - b["z"][:, 1:]) ** 2).sum(-1)[keep].numpy())
    return np.concatenate(errs), np.concatenate(z_errs)


@torch.no_grad()
def dream_advantages(agent: G.Agent, replay: G.Replay, args: G.Args) -> dict:
    """Lambda-returns and advantages in dreams from replayed 64 x 32 batches, from every replayed state
    (more dreams than one update makes, for steadier shares)."""
    b = {k: torch.as_tensor(v) for k, v in replay.sample(64, 32).items()}
    h_entry = G.world_model_loss(agent.wm, agent.reward_dec, b, args)[2]
    h0, z0, _ = G.dream_starts(h_entry, b, "all")
    feats, acts, rews, conts, _ = G.imagine(agent, h0, z0, 20)
    values = agent.twohot.mean(agent.critic(feats))
    returns = G.lambda_returns(rews, conts, values, args.gamma, args.lam)
    adv, taken = returns - values[:-1], acts.argmax(-1)
    per_action = {
        k: (float((taken == k).float().mean()), float(adv[taken == k].mean())) for k in range(N_ACTIONS)
    }
    return {
        "return": float(returns.mean()),
        "adv": (float(adv.mean()), float(adv.std())),
        "per_action": per_action,
    }


def reward_from_true_z(agent: G.Agent, replay: G.Replay, seed: int, steps: int = 3_000) -> float:
    """Held-out mean |r_hat - r| of a fresh reward head (2 x 256, two-hot) fitted to (z_{t+1}, r_{t+1})."""
    n = int(min(replay.count[0], replay.cap))
    keep = np.flatnonzero(replay.last[0, : n - 1] == 0)
    z_next, r = torch.as_tensor(replay.z[0, keep + 1]), torch.as_tensor(replay.r[0, keep])
    gen = torch.Generator().manual_seed(seed)
    perm = torch.randperm(len(keep), generator=gen)
    test, train = perm[:3_000], perm[3_000:]
    head = G.mlp(z_next.shape[1], 256, 255, 2)
    opt = torch.optim.Adam(head.parameters(), lr=1e-3)
    for _ in range(steps):
        b = train[torch.randint(len(train), (512,), generator=gen)]
        loss = agent.twohot.loss(head(z_next[b]), r[b]).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return float((agent.twohot.mean(head(z_next[test])) - r[test]).abs().mean())


@torch.no_grad()
def z_change_per_action(encoder, n: int, seed: int) -> np.ndarray:
    """||z(s') - z(s)||^2 for each action 1-6 from n reset states s (rows), s' = s after the action."""
    env, out = SimpleShapesVectorEnv(1), []
    for i in range(n):
        env.reset(seed=seed + i)
        core = env._core
        state = {k: getattr(core, k)[:1].copy() for k in ("cls", "size", "rgb")}
        # one pixel inside the start range, so that every moved state is one the env accepts
        (x, y), rot = np.clip(core.pos[0], 8, 23), core.rotation[0]
        obs, _ = env.reset(options={"state": state | {"x": [x], "y": [y], "rotation": [rot]}})
        z0 = encoder(obs)
        row = []
        for dx, dy, dr in ACTION_DELTAS[1:]:
            moved = {"x": [x + dx], "y": [y + dy], "rotation": [np.mod(rot + dr, 2 * np.pi)]}
            obs, _ = env.reset(options={"state": state | moved})
            row.append(float(((encoder(obs) - z0) ** 2).sum()))
        out.append(row)
    env.close()
    return np.array(out)


@torch.no_grad()
def random_action_reward_error(agent, encoder, args, a: Args) -> tuple[np.ndarray, float]:
    """Per-action |r_hat - r| one step ahead from states reached by random actions, and the share of
    states where argmax r_hat is a truly best action."""
    env = G.make_envs(args, 1)
    core, rng, eye = env._core, np.random.default_rng(a.seed), torch.eye(N_ACTIONS)
    errs, agree = [], []
    for ep in range(a.episodes):
        obs, _ = env.reset(seed=a.seed + ep)
        h = torch.zeros(1, agent.wm.hidden)
        for t in range(a.steps):
            z = encoder(obs)
            h_all = agent.wm.step(h.repeat(N_ACTIONS, 1), z.repeat(N_ACTIONS, 1), eye)
            r_hat = agent.reward_dec.value(agent.wm.heads(h_all)[1]).numpy()
            pos = core.pos[0] + ACTION_DELTAS[:, :2]
            rot = np.mod(core.rotation[0] + ACTION_DELTAS[:, 2], 2 * np.pi)
            r_true = reward_and_goal(pos, rot, core.coef)[0]
            if t > 0:  # the first step's h = 0 has seen nothing
                errs.append(np.abs(r_hat - r_true))
                agree.append(r_true[np.argmax(r_hat)] >= r_true.max() - 1e-6)
            act = int(rng.integers(N_ACTIONS))
            h = agent.wm.step(h, z, eye[act : act + 1])
            obs, _, term, trunc, _ = env.step(np.array([act]))
            if term[0] or trunc[0]:
                break
    env.close()
    return np.array(errs), float(np.mean(agree))


@torch.no_grad()
def greedy_episodes(agent, encoder, args, a: Args) -> tuple[np.ndarray, float]:
    """Greedy-policy returns and the share of rotation actions (5, 6) among its actions."""
    env = G.make_envs(args, 1)
    returns, actions = [], []
    for ep in range(a.episodes):
        obs, _ = env.reset(seed=a.seed + 10_000 + ep)
        h, ret, done = torch.zeros(1, agent.wm.hidden), 0.0, False
        while not done:
            z = encoder(obs)
            act = agent.actor.act(agent.features(h, z), mode=True)
            obs, r, term, trunc, _ = env.step(G.action_for_env(act, True))
            ret += float(r[0])
            actions.append(int(act.argmax()))
            done = bool(term[0] or trunc[0])
            h = agent.wm.step(h, z, act)
        returns.append(ret)
    env.close()
    return np.array(returns), float(np.isin(actions, (5, 6)).mean())


if __name__ == "__main__":
    a = tyro.cli(Args)
    encoder = G.load_encoder("simple_shapes", Path(a.vae_checkpoint), Path(a.gw_checkpoint))
    saved = torch.load(a.checkpoint, map_location="cpu", weights_only=False)["args"]
    # the agent's own network settings, experiments included (benchmarks/experiments/)
    args = X.Args(
        env="simple_shapes", **{k: saved[k] for k in ("reward_loss", *G.EXPERIMENT_KEYS) if k in saved}
    )
    ck = G.load_agent_checkpoint(Path(a.checkpoint), args.resolve(), G.gw_fingerprint(encoder))
    agent = X.experiment_agent(args)("simple_shapes", encoder.z_dim, args.reward_loss)
    agent.load_state_dict(ck["agent"])
    agent.eval()
    replay = G.Replay(args.buffer_size, 1, encoder.z_dim, N_ACTIONS, a.seed)
    replay.load_state_dict(ck["replay"])
    torch.manual_seed(a.seed)
    print(f"{a.checkpoint}: {ck['state']['env_steps']:,} env steps, {ck['state']['updates']:,} updates")

    n = int(min(replay.count[0], replay.cap))
    oldest = int(replay.pos[0]) if replay.count[0] > replay.cap else 0  # a full buffer has wrapped
    a_t, last = np.roll(replay.a[0, :n], -oldest, 0), np.roll(replay.last[0, :n], -oldest)
    acts = a_t.argmax(-1)[last == 0]  # one entry per env step of the stored window
    print("1. actions taken (share; 0 no-op, 1 x+1, 2 y+1, 3 x-1, 4 y-1, 5/6 rotate):")
    for lo, hi in zip(a.windows[:-1], a.windows[1:], strict=True):
        part = acts[lo:hi]
        if len(part):
            shares = " ".join(f"{np.mean(part == k):.2f}" for k in range(N_ACTIONS))
            print(f"   env steps {lo:>6,}-{hi:<6,}: {shares}")

    err, z_err = replay_errors(agent, replay)
    print(f"2. reward error on replayed sequences: mean {err.mean():.2f}, median {np.median(err):.2f}")
    per_action, agree = random_action_reward_error(agent, encoder, args, a)
    print(
        "   one step ahead under random actions, mean per action: "
        + " ".join(f"{e:.2f}" for e in per_action.mean(0))
        + f" (median over all {np.median(per_action):.2f});"
        + f" best action rated best in {agree:.0%} of {len(per_action)} states"
    )
    rets, rot_share = greedy_episodes(agent, encoder, args, a)
    lo_ref, hi_ref = G.ss_reference_returns()
    sem, normalised = rets.std(ddof=1) / np.sqrt(len(rets)), (rets.mean() - lo_ref) / (hi_ref - lo_ref)
    print(
        f"3. greedy policy, {a.episodes} episodes: return {rets.mean():.1f} ± {sem:.1f}, "
        f"normalised {normalised:.3f}"
        f", rotation actions {rot_share:.0%} of its actions"
    )
    moves = z_change_per_action(encoder, 300, a.seed)
    print(
        "4. ||z' - z||^2 for one action, median per action 1-6: "
        + " ".join(f"{m:.4f}" for m in np.median(moves, 0))
        + f"; world model's one-step ||z_hat - z||^2 on replayed sequences: mean {z_err.mean():.4f},"
        f" median {np.median(z_err):.4f}"
    )
    fitted = reward_from_true_z(agent, replay, a.seed)
    print(f"5. reward read from the true next z by a freshly fitted head: mean error {fitted:.2f} (held out)")
    d = dream_advantages(
        agent, replay, G.Args(env="simple_shapes", **{k: ck["args"][k] for k in ("gamma", "lam")})
    )
    print(
        f"6. dreams: mean lambda-return {d['return']:.1f}, return scale {float(agent.return_scale.ema):.1f}, "
        f"advantage {d['adv'][0]:.1f} ± {d['adv'][1]:.1f} (mean ± std); per action (share, mean advantage): "
        + " ".join(f"{k}:({share:.3f}, {mean:.1f})" for k, (share, mean) in d["per_action"].items())
    )
