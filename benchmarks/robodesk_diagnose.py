"""What a RoboDesk GW-Dreamer agent checkpoint has learnt, for runs that stall below the criterion.

1. Actor saturation. Under dynamics backpropagation the actor's mean m can grow until tanh(m) sits at the
   action bound, where its gradient vanishes and the policy can no longer change (docs/gw_dreamer.md,
   "RoboDesk on a CPU"). On the newest states of replayed sequences (the states dreams start from): the
   median and 90th percentile of |m|, the share of means with |tanh(m)| > 0.99, the mean action and std
   per dimension, and the share of the last 2,000 stored actions at a bound. Alternation: the share of
   consecutive stored steps whose x, y or z action reverses (a_t a_{t+1} < -0.25), per 10,000 frames of
   the run; a policy that learnt a period-2 reply to its own last action (the actor differentiated
   through the dreamt states it reads) pushes it from a few % to 10-40% while the arm stops moving.
   Actions as the world model sees them: per 50,000 frames of the run, the held-out R^2 of the stored
   action predicted from (z_t, a_{t-1}) (ridge regression on those and 256 random tanh features, 80/20
   split) and the std of what it leaves unexplained, per action dimension. A world model learns what an
   action does only from the part of it the state does not already predict.
2. The world model's reward on the agent's own data: after 64 real steps of a replayed sequence, the
   next 20 rewards predicted one step ahead (real z read each step) and open loop (its own z fed back,
   as in a dream) with the actions that were taken, against the real rewards: mean |r_hat - r| at
   horizons 1, 5, 10 and 20, and the correlation of the 20-step sums; the one-step predictions at the
   reward's upward jumps (push_green: the light coming on).
3. Whether the world model knows what other actions would do: in --counterfactual-states states reached
   by the agent's own policy (fresh episodes, fast images), seven first actions (none, and +-1 along
   each of x, y, z), each followed by 4 steps without action, run in the simulator from the same state
   and dreamt by the world model from the agent's h and z there; the rank correlation of the seven
   5-step reward sums, true against dreamt (1: the world model orders the actions as the simulator
   does), and the spread of those sums across the actions.
4. Pressing (push_green): in --press-episodes episodes from fixed starts, the share of steps with the light
   on, the reward per agent step, the share of steps within 8 cm of the button and, within 4 cm, how often
   the gripper action is closed / mid / open and how often the light is on for each; from states within
   4 cm with the light off, the true and the dreamt 10-step reward of pushing down with the gripper
   closed against keeping still.
   --press-tolerance adds the scripted expert aimed off the button's centre at five gripper settings
   (what pressing takes).
5. What the GW carries on the agent's own states (--gw-coverage N): along N of the agent's episodes
   (fixed starts) and N of the scripted push_green expert's (action noise 0.1, like the GW's data), the
   end effector and the green light read from z through d_attr and the attribute VAE's decoder, against
   the simulator's: the end effector's mean error in cm (within 15 cm of the button in brackets) and the
   correlation of the light joint's read-out with the real one, for the fused z, z from vision alone and
   z from the attributes alone. --gw-dirs adds other pretrain_vae_gw.py outputs (their robodesk/vae.pt
   and gw.pt) read on the same observations; the agent acts on its own GW. --coverage-data adds how far
   the agent's arm poses lie from a pretrain_vae_gw.py dataset (its <data_dir>/robodesk/ shards): the
   median distance from each of the agent's robot joint configurations (the 9 qpos, in units of the
   data's std) to the nearest one of each data source (expert, random, wanderer), against the same for
   the data's held-out episodes of that source, and each GW's end-effector read-out on those held-out
   episodes, per source.

6. Whether reward carries from some agents' states to another's (--reward-transfer N, two checkpoints or
   more on the same GW): N episodes of each agent (fixed starts); a reward head (2 x 256, 3,000 Adam
   steps) fit on all agents but one, reading the next state's z (fused, vision only, attributes only) or
   the true attributes (standardised), and its mean |r_hat - r| per agent step on the left-out agent's
   steps, averaged over the agents left out. If the true attributes do no better than z, a head fit on a
   few policies' states extrapolates poorly whatever it reads, and the test does not single out z.

7. How the return spreads over episodes (--spread-episodes N, push_green or another task with a scripted
   expert): N episodes from fixed starts (seeds 900, 901, ...) acted three ways: as the run collects
   (actions sampled, plus the run's --explore-noise; the criterion's episodes), the same with the same
   random draws but h_t rebuilt at every step from h = 0 over the last --batch-length steps (the longest
   history a replayed h_t has read in training, while acting carries h over the whole episode), and as
   the run evaluates (the actor's mode, no noise). Per way: the normalised return's mean and s.e.m. and
   the episodes below 0 (worse than the random policy); for those against the rest, the end effector's
   distance to the task's target at the start and the share of steps with a robot joint within 0.1 rad
   of its bound. Equal returns in the first two ways clear the GRU state's long history as a cause.

8. The critic against the returns the agent really got (--critic-bias N): along the newest N whole
   episodes of the replay, h_t filtered from their stored z and actions as when acting, the critic's value
   V(h_t) against the discounted return of the stored rewards from t to the episode's end, bootstrapped
   there from the critic (the episodes end by time limit), grouped by the reward of the step before
   (a button task: push_green, push_red or push_blue; per agent step: above 3.05 the light was on;
   2.7-3.05 near the button, unpressed; below, farther). A critic that tracks the real returns has V - G
   near 0 in every group and the same gaps between groups as G.

9. Reaching and moving the object (--object-episodes N; open_slide, open_drawer): in N episodes from
   fixed starts (seeds 950, 951, ...) for the agent (acting as the run evaluates it), the uniformly
   random policy (the normalised return's 0) and the task's scripted expert (its 1): the end effector's
   closest approach to the contact point (the expert's way-point from which it pushes the slide or pulls
   the drawer), the largest movement of the slide or drawer from where the episode started, and the
   success count. An agent that never moves the object never meets the reward that opening it pays
   (about three quarters of the dense reward), only the reward for nearing it.

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
    counterfactual_states: int = 8
    """states of part 3 (0 skips it: it needs MuJoCo's renderer and the agent's VAEs + GW)"""
    press_episodes: int = 4
    """episodes of part 4 (fixed starts, seeds 700, 701, ...; 0 skips it)"""
    gw_coverage: int = 0
    """episodes of part 5 (0 skips it)"""
    gw_dirs: tuple[str, ...] = ()
    """part 5: checkpoint directories of other VAEs + GWs to read the same observations with"""
    coverage_data: str = ""
    """part 5: a pretrain_vae_gw.py --data-dir whose robot joint configurations are compared with the
    agent's"""
    reward_transfer: int = 0
    """episodes per checkpoint of part 6 (0 skips it)"""
    spread_episodes: int = 0
    """episodes of part 7 for each of its three ways (0 skips it)"""
    critic_bias: int = 0
    """newest replayed episodes of part 8 (0 skips it)"""
    object_episodes: int = 0
    """episodes of part 9 for each of its three policies (0 skips it)"""
    press_tolerance: bool = False
    """also print what pressing takes: the scripted expert aimed off the button's centre, at each gripper
    setting (part 4's reference; the same for every checkpoint)"""


def has_done_head(ck: dict) -> bool:
    """Whether an agent checkpoint's world model has a done head (--done-head on), read from its weights:
    a checkpoint saved before the flag existed does not record it."""
    return any(k.startswith("wm.done_head.") for k in ck["agent"])


def read_checkpoint(path: str) -> dict:
    """The gw_dreamer.py RoboDesk agent checkpoint at ``path``; anything else stops with a one-line error."""
    try:
        ck = torch.load(path, weights_only=False, map_location="cpu")
    except FileNotFoundError:
        raise SystemExit(f"error: {path} does not exist") from None
    except Exception as err:  # not a file torch.save wrote: unpickling, zip or end-of-file errors
        raise SystemExit(f"error: {path} is not a torch checkpoint ({type(err).__name__})") from None
    if not isinstance(ck, dict) or ck.get("kind") != "gw_dreamer" or ck.get("env") != "robodesk":
        raise SystemExit(f"error: {path} is not a gw_dreamer.py RoboDesk agent checkpoint")
    return ck


def replay_agent(ck: dict):
    """The agent of the gw_dreamer.py RoboDesk checkpoint ``ck`` (``read_checkpoint``'s) and its run's
    settings."""
    args = G.Args(**{k: v for k, v in ck["args"].items() if k in G.Args.__dataclass_fields__}).resolve()
    z_dim = ck["replay"]["z"].shape[-1]
    agent = G.Agent(
        "robodesk", z_dim, args.reward_loss, args.return_norm_decay, args.cpu_preset, has_done_head(ck)
    )
    agent.load_state_dict(ck["agent"])
    return agent, args


@torch.no_grad()
def saturation(path: str, sequences: int, seed: int) -> dict:
    ck = read_checkpoint(path)
    agent, args = replay_agent(ck)
    z_dim = ck["replay"]["z"].shape[-1]
    replay = G.Replay(args.buffer_size, args.num_envs, z_dim, G.SIZES["robodesk"]["actions"], seed)
    state = ck["replay"] | {"rng": np.random.default_rng(seed).bit_generator.state}
    replay.load_state_dict(state)
    batch = {k: torch.as_tensor(v) for k, v in replay.sample(sequences, args.batch_length).items()}
    _, terms, h_entry, _ = G.world_model_loss(agent.wm, agent.reward_dec, batch, args)
    m, s = agent.actor.net(h_entry[:, -1]).chunk(2, -1)
    mean, std = torch.tanh(m), 0.9 * torch.sigmoid(s + 2.0) + 0.1
    count = int(ck["replay"]["count"][0])
    stored = ck["replay"]["a"][0][:count][-2000:]
    out = open_loop_rewards(agent, ck["replay"], seed) | press_onsets(agent, ck["replay"])
    first = ck["replay"]["first"][0][:count]
    actions = ck["replay"]["a"][0][:count]
    flips = []  # per 2,500 agent steps (10,000 frames): consecutive x/y/z actions of opposite sign
    for lo in range(0, count - 1, 2500):
        a, keep = actions[lo : lo + 2501], first[lo + 1 : lo + 2501] == 0
        flips.append(float(((a[:-1, :3] * a[1:, :3]) < -0.25)[keep].mean()))
    return out | {
        "predictability": action_predictability(ck["replay"]),
        "env_steps": ck["state"]["env_steps"],
        "loss_z": float(terms["loss_z"]),
        "m_median": float(m.abs().median()),
        "m_p90": float(m.abs().quantile(0.9)),
        "at_bound": float((mean.abs() > 0.99).float().mean()),
        "mean": mean.mean(0).numpy(),
        "std": std.mean(0).numpy(),
        "stored_at_bound": (np.abs(stored) >= 0.999).mean(0),
        "reversals": np.array(flips),
    }


@torch.no_grad()
def action_predictability(replay: dict, chunk: int = 12_500) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Part 1: per `chunk` stored agent steps (50,000 frames), (its first frame, held-out R^2 of a_t from
    (z_t, a_{t-1}) per action dimension, std of the residual per dimension)."""
    count = int(replay["count"][0])
    z, a = replay["z"][0][:count].astype(np.float64), replay["a"][0][:count].astype(np.float64)
    first, last = replay["first"][0][:count] > 0, replay["last"][0][:count] > 0
    a_prev = np.concatenate([np.zeros_like(a[:1]), a[:-1]])
    a_prev[first] = 0.0
    x = np.concatenate([z, a_prev, np.ones((count, 1))], 1)
    w = np.random.default_rng(0).normal(size=(x.shape[1], 256)) / np.sqrt(x.shape[1])
    x = np.concatenate([x, np.tanh(2 * x @ w)], 1)
    out = []
    for lo in range(0, count, chunk):
        idx = np.flatnonzero(~last[lo : lo + chunk]) + lo  # an episode's final entry holds no action
        if len(idx) < 1000:
            break
        idx = np.random.default_rng(lo).permutation(idx)
        fit, test = idx[: len(idx) * 4 // 5], idx[len(idx) * 4 // 5 :]
        coef = np.linalg.solve(x[fit].T @ x[fit] + np.eye(x.shape[1]), x[fit].T @ a[fit])
        resid = a[test] - x[test] @ coef
        r2 = 1 - (resid**2).sum(0) / ((a[test] - a[test].mean(0)) ** 2).sum(0)
        out.append((4 * lo, r2, resid.std(0)))
    return out


def press_onsets(agent, replay: dict, newest: int = 20_000) -> dict:
    """One-step reward predictions (the real z read at every step) over the newest entries of the first
    replay stream, at the steps where the reward jumps by more than 0.5 (push_green: the light comes on)
    and elsewhere: real and predicted means."""
    count = int(replay["count"][0])
    lo = max(0, count - newest)
    z, a, r, first = (torch.as_tensor(replay[k][0][lo:count]) for k in ("z", "a", "r", "first"))
    h, pred = torch.zeros(1, agent.wm.hidden), []
    for t in range(len(z)):
        h = torch.zeros_like(h) if first[t] else h
        h = agent.wm.step(h, z[t : t + 1], a[t : t + 1])
        pred.append(float(agent.reward_dec.value(agent.wm.heads(h)[1])))
    pred, r, first = np.array(pred), r.numpy(), first.numpy()
    jump = np.r_[0.0, np.diff(r)] * np.r_[0.0, first[1:] == 0]
    onset, rest = jump > 0.5, np.abs(jump) < 0.2
    before = np.r_[onset[1:], False]  # the step before each onset
    return {
        "onsets": int(onset.sum()),
        "onset_real": r[onset].mean() if onset.any() else float("nan"),
        "onset_pred": pred[onset].mean() if onset.any() else float("nan"),
        "onset_before": r[before].mean() if onset.any() else float("nan"),
        "rest_err": np.abs(pred - r)[rest].mean(),
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


def agent_in_simulator(path: str, task: str | None = None):
    """Parts 3 and 4: a checkpoint's agent, the frozen VAEs + GW it reads, and a RoboDesk env of its task
    (or ``task``) rendering the images its GW was trained on."""
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")
    from envs.robodesk import RoboDeskEnv

    ck = read_checkpoint(path)
    args = G.Args(**{k: v for k, v in ck["args"].items() if k in G.Args.__dataclass_fields__}).resolve()
    encoder, _ = G.load_frozen(args, torch.device("cpu"))
    z_dim, done_head = encoder.z_dim, has_done_head(ck)
    agent = G.Agent("robodesk", z_dim, args.reward_loss, args.return_norm_decay, args.cpu_preset, done_head)
    agent.load_state_dict(ck["agent"])
    env = RoboDeskEnv(
        task=task or args.task, render_quality=args.render_quality, episode_length=args.episode_length
    )
    return agent, encoder, env


@torch.no_grad()
def counterfactual_actions(path: str, n_states: int, follow: int = 4) -> dict:
    """Part 3: true and dreamt 5-step rewards of seven first actions from states the policy reaches."""
    agent, encoder, env = agent_in_simulator(path)
    firsts = [np.zeros(5, np.float32)]
    for d in range(3):
        for sign in (1.0, -1.0):
            firsts.append(np.eye(5, dtype=np.float32)[d] * sign)
    still = [np.zeros(5, np.float32)] * follow
    corr, spread_true, spread_dream = [], [], []
    for i in range(n_states):
        obs, _ = env.reset(seed=1000 + i)
        h = torch.zeros(1, agent.wm.hidden)
        for _ in range(40 + 10 * i):  # states at agent steps 40, 50, 60, ...
            z = encoder({k: v[None] for k, v in obs.items()})
            a = agent.actor.act(agent.features(h, z))
            obs, *_ = env.step(a[0].numpy())
            h = agent.wm.step(h, z, a)
        qpos, qvel, z0 = (
            env.data.qpos.copy(),
            env.data.qvel.copy(),
            encoder({k: v[None] for k, v in obs.items()}),
        )
        true, dreamt = [], []
        for first in firsts:
            env.set_state(qpos, qvel)
            true.append(sum(env.step(x)[1] for x in [first, *still]))
            hh, zz, total = h, z0, 0.0
            for x in [first, *still]:
                hh = agent.wm.step(hh, zz, torch.as_tensor(x)[None])
                zz, r_out, _ = agent.wm.heads(hh)
                total += float(agent.reward_dec.value(r_out))
            dreamt.append(total)
        true, dreamt = np.array(true), np.array(dreamt)
        ranks = [np.argsort(np.argsort(x)) for x in (true, dreamt)]
        corr.append(float(np.corrcoef(*ranks)[0, 1]))
        spread_true.append(np.ptp(true))
        spread_dream.append(np.ptp(dreamt))
    env.close()
    return {
        "rank_corr": float(np.mean(corr)),
        "rank_corr_sem": float(np.std(corr, ddof=1) / np.sqrt(len(corr))) if len(corr) > 1 else 0.0,
        "spread_true": float(np.mean(spread_true)),
        "spread_dream": float(np.mean(spread_dream)),
    }


GRIP = {"closed": (-1.0, -0.3), "mid": (-0.3, 0.3), "open": (0.3, 1.0)}  # gripper action (+1 opens)


@torch.no_grad()
def pressing(path: str, episodes: int) -> dict:
    """Part 4: where the agent's own episodes spend their steps around the green button. The press bonus
    (a quarter of the dense reward) needs the closed gripper pushed down within a few cm of the button
    (--press-tolerance); hovering above it earns the distance part alone. Per step: horizontal distance
    end effector to button, the gripper action, whether the light is on. Every 7th step within 4 cm with the
    light off, ``hover_probe`` asks the simulator and the dream what pushing down would pay."""
    agent, encoder, env = agent_in_simulator(path, task="push_green")
    lo, hi = env.joint_bounds[6]
    wrist_still = -(lo + hi) / (hi - lo)  # the wrist action whose step is 0
    rows = []  # x, y offset, xy distance, height above the button (cm), gripper action, light, reward
    probes = []  # (true, dreamt) 10-step reward sums of "down" and "still", true light share of "down"
    for ep in range(episodes):
        obs, _ = env.reset(seed=700 + ep)
        h, done, t = torch.zeros(1, agent.wm.hidden), False, 0
        while not done:
            z = encoder({k: v[None] for k, v in obs.items()})
            a = agent.actor.act(agent.features(h, z))
            d = 100 * (env.data.site_xpos[env._ee_site] - env._xpos("green_button"))
            if np.linalg.norm(d[:2]) < 4 and not env.task_reward("success") and t % 7 == 0 and t < 480:
                down = np.array([0, 0, -1, wrist_still, -1], np.float32)
                still = np.array([0, 0, 0, wrist_still, float(a[0, 4])], np.float32)
                probes.append(hover_probe(env, agent, encoder, h, z, (down, still)))
            obs, r, term, trunc, _ = env.step(a[0].numpy())
            t += 1
            rows.append((*d[:2], np.linalg.norm(d[:2]), d[2], float(a[0, 4]), env.task_reward("success"), r))
            h, done = agent.wm.step(h, z, a), term or trunc
    env.close()
    dx, dy, xy, dz, grip, pressed, r = np.array(rows).T
    out = {"pressed": pressed.mean(), "reward": r.mean(), "near": (xy < 8).mean()}
    for name, (lo, hi) in GRIP.items():
        m = (xy < 4) & (grip >= lo) & (grip <= hi)
        out[f"share_{name}"], out[f"pressed_{name}"] = m.sum() / max((xy < 4).sum(), 1), pressed[m].mean()
    closed = (xy < 4) & (grip < GRIP["closed"][1])
    for name, m in (("on", closed & (pressed > 0)), ("off", closed & (pressed == 0))):
        out[f"height_{name}"] = np.median(dz[m]) if m.any() else float("nan")
        out[f"offset_{name}"] = np.array([dx[m].mean(), dy[m].mean()]) if m.any() else np.full(2, np.nan)
    if probes:
        out["probes"] = len(probes)
        true, dreamt, light, steps_true, steps_dream, moved_true, moved_dream = zip(*probes, strict=True)
        out |= {"probe_true": np.mean(true, 0), "probe_dream": np.mean(dreamt, 0)}
        out |= {"probe_steps_true": np.mean(steps_true, 0), "probe_steps_dream": np.mean(steps_dream, 0)}
        out |= {"probe_moved_true": np.mean(moved_true, 0), "probe_moved_dream": np.mean(moved_dream, 0)}
        out["probe_light"] = np.mean(light)
    return out


@torch.no_grad()
def hover_probe(env, agent, encoder, h, z, plans, steps: int = 10) -> tuple:
    """From a state near the button with the light off: the true and the dreamt reward over ``steps`` agent
    steps of each fixed action in ``plans`` (the dream from the agent's own h and z there); for the first
    plan, the share of steps with the light on, the true and dreamt reward of each step, and how far the
    end effector moved (x, y, z in cm; the dream's read from its z through the GW's attribute decoder).
    The simulator is put back afterwards."""
    qpos, qvel, count = env.data.qpos.copy(), env.data.qvel.copy(), env._num_steps
    ee0 = env.data.site_xpos[env._ee_site].copy()
    true, dreamt, first = [], [], {}
    for i, action in enumerate(plans):
        env.set_state(qpos, qvel)
        env._num_steps = count
        on = [(env.step(action)[1], env.task_reward("success")) for _ in range(steps)]
        true.append(sum(r for r, _ in on))
        hh, zz, dreamt_steps = h, z, []
        for _ in range(steps):
            hh = agent.wm.step(hh, zz, torch.as_tensor(action)[None])
            zz, r_out, _ = agent.wm.heads(hh)
            dreamt_steps.append(float(agent.reward_dec.value(r_out)))
        dreamt.append(sum(dreamt_steps))
        if i == 0:
            moved_true = 100 * (env.data.site_xpos[env._ee_site] - ee0)
            moved_dream = 100 * (decoded_end_effector(encoder, zz) - decoded_end_effector(encoder, z))
            moved_true, moved_dream = (np.r_[np.abs(m[:2]), m[2]] for m in (moved_true, moved_dream))
            first = dict(light=np.mean([x for _, x in on]), steps_true=[r for r, _ in on])
            first |= dict(steps_dream=dreamt_steps, moved_true=moved_true, moved_dream=moved_dream)
    env.set_state(qpos, qvel)
    env._num_steps = count
    return (np.array(true), np.array(dreamt), *first.values())


@torch.no_grad()
def gw_coverage(path: str, episodes: int, gw_dirs: tuple[str, ...]) -> dict:
    """Part 5: {(GW, policy, z's modality): (end-effector error cm, the same within 15 cm of the button,
    correlation of the light joint's read-out with the real one)}."""
    from envs.robodesk import N_ROBOT_JOINTS as N
    from envs.robodesk_experts import EXPERTS

    agent, encoder, env = agent_in_simulator(path, task="push_green")
    ck = read_checkpoint(path)
    encoders = {"the agent's GW": encoder}
    for folder in gw_dirs:
        a = G.Args(**{k: v for k, v in ck["args"].items() if k in G.Args.__dataclass_fields__}).resolve()
        a.checkpoint_dir = folder
        encoders[folder] = G.load_frozen(a, torch.device("cpu"))[0]
    joint = env.model.joint("green_light").qposadr[0]
    light = 2 * N + 3 + joint - N  # the attributes: qpos[:N], qvel[:N], end effector, qpos[N:], qvel[N:]
    modes = {"fused": (0.5, 0.5), "vision": (1.0, 0.0), "attributes": (0.0, 1.0)}
    out, seen = {}, {}
    for policy in ("agent", "expert"):
        read = {(g, m): [] for g in encoders for m in modes}
        truth, near = [], []
        for ep in range(episodes):
            obs, _ = env.reset(seed=700 + ep)
            expert = EXPERTS["push_green"](env, noise=0.1, seed=ep) if policy == "expert" else None
            h, done = torch.zeros(1, agent.wm.hidden), False
            while not done:
                batch = {k: v[None] for k, v in obs.items()}
                for g, enc in encoders.items():
                    for m, (alpha_v, alpha_attr) in modes.items():
                        attr = enc.vae_attr.decoder(enc.gw.d["attr"](enc(batch, alpha_v, alpha_attr)))
                        read[g, m].append((attr * enc.attr_std + enc.attr_mean)[0].numpy())
                truth.append(obs["attr"])
                near.append(np.linalg.norm(obs["attr"][18:21] - env._xpos("green_button")) < 0.15)
                z = encoder(batch)
                if expert is None:
                    a = agent.actor.act(agent.features(h, z))
                else:
                    a = torch.as_tensor(expert.act(env))[None]
                obs, _, term, trunc, _ = env.step(a[0].numpy())
                h, done = agent.wm.step(h, z, a), term or trunc
        truth, near = np.array(truth), np.array(near)
        seen[policy] = truth
        for (g, m), rows in read.items():
            rows = np.array(rows)
            err = 100 * np.linalg.norm(rows[:, 18:21] - truth[:, 18:21], axis=1)
            corr = np.corrcoef(rows[:, light], truth[:, light])[0, 1]
            out[g, policy, m] = (err.mean(), err[near].mean() if near.any() else np.nan, corr)
    env.close()
    return out, seen["agent"], encoders


@torch.no_grad()
def held_out_by_source(encoders: dict, data_dir: str, held_out: int = 6_000) -> dict:
    """Part 5, --coverage-data: {(GW, data source, z's modality): mean end-effector error in cm} on the
    data's held-out front (whole episodes), read as for the agents' episodes."""
    data = np.load(sorted((Path(data_dir) / "robodesk").glob("shard_*.npz"))[0])
    image, attr, source = data["image"][:held_out], data["attr"][:held_out], data["source"][:held_out]
    modes = {"fused": (0.5, 0.5), "vision": (1.0, 0.0), "attributes": (0.0, 1.0)}
    out = {}
    for g, enc in encoders.items():
        for src in np.unique(source):
            keep = np.nonzero(source == src)[0]
            for m, alphas in modes.items():
                read = []
                for i in range(0, len(keep), 500):
                    rows = keep[i : i + 500]
                    z = enc({"image": image[rows], "attr": attr[rows]}, *alphas)
                    read.append(
                        (enc.vae_attr.decoder(enc.gw.d["attr"](z)) * enc.attr_std + enc.attr_mean).numpy()
                    )
                err = np.linalg.norm(np.concatenate(read)[:, 18:21] - attr[keep, 18:21], axis=1)
                out[g, str(src), m] = 100 * float(err.mean())
    return out


# Arm poses the scripted experts' data lack and learning agents take (docs/pretrain_vae_gw.md): the wrist
# (joint 7, qpos 6) near either end of its range, and joint 6 (qpos 5) bent, the hand pressed on the desk.
POSES = {
    "wrist < -2.4 rad": lambda q: q[:, 6] < -2.4,
    "wrist > 1.5 rad": lambda q: q[:, 6] > 1.5,
    "joint 6 < 1 rad": lambda q: q[:, 5] < 1.0,
}


def pose_shares(agent_attr: np.ndarray, data_dir: str) -> dict:
    """Part 5, --coverage-data: {"agent" or data source: {pose: share of the steps in it}}."""
    shards = sorted((Path(data_dir) / "robodesk").glob("shard_*.npz"))
    qpos = np.concatenate([np.load(f)["attr"][:, :9] for f in shards])
    source = np.concatenate([np.load(f)["source"] for f in shards])
    groups = {"agent": agent_attr[:, :9]} | {str(s): qpos[source == s] for s in np.unique(source)}
    return {g: {name: float(test(q).mean()) for name, test in POSES.items()} for g, q in groups.items()}


def joint_coverage(agent_attr: np.ndarray, data_dir: str, held_out: int = 6_000, n: int = 60_000) -> dict:
    """Part 5, --coverage-data: {data source: (median distance from the agent's robot joint configurations
    to the nearest of that source's, the same from the source's held-out episodes)}, in units of the
    data's std per joint. The held-out episodes are the data's first ``held_out`` samples (whole episodes:
    pretrain_vae_gw.py's held-out front); the rest, at most ``n`` per source, are the pool. A neighbour
    in the same episode would sit a step away, so only whole held-out episodes say how near a new episode
    of the same kind comes."""
    from envs.robodesk import N_ROBOT_JOINTS as N

    shards = sorted((Path(data_dir) / "robodesk").glob("shard_*.npz"))
    if not shards:
        raise SystemExit(f"--coverage-data: no shard_*.npz in {Path(data_dir) / 'robodesk'}")
    qpos = np.concatenate([np.load(f)["attr"][:, :N] for f in shards])
    source = np.concatenate([np.load(f)["source"] for f in shards])
    std, rng = qpos.std(0) + 1e-6, np.random.default_rng(0)

    def nearest(points: np.ndarray, pool: np.ndarray) -> float:
        pool = torch.as_tensor(pool / std, dtype=torch.float32)
        return float(
            torch.cdist(torch.as_tensor(points / std, dtype=torch.float32), pool).min(1).values.median()
        )

    agent = agent_attr[:, :N]
    out = {}
    for src in np.unique(source):
        pool = qpos[held_out:][source[held_out:] == src]
        pool = pool[rng.choice(len(pool), min(n, len(pool)), replace=False)]
        held = qpos[:held_out][source[:held_out] == src]
        out[str(src)] = (nearest(agent, pool), nearest(held, pool) if len(held) else float("nan"))
    return out


@torch.no_grad()
def agent_episodes(path: str, episodes: int, seed: int) -> dict:
    """Part 6: ``episodes`` of the checkpoint's agent from fixed starts: {"z": fused, vision, attributes
    z of each observation, "attr": attributes, "next": index of the next observation, "r": reward}."""
    agent, encoder, env = agent_in_simulator(path, task="push_green")
    modes = {"fused": (0.5, 0.5), "vision": (1.0, 0.0), "attributes": (0.0, 1.0)}
    z, attr, nxt, r = {m: [] for m in modes}, [], [], []
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        h, done = torch.zeros(1, agent.wm.hidden), False
        while True:
            batch = {k: v[None] for k, v in obs.items()}
            for m, alphas in modes.items():
                z[m].append(encoder(batch, *alphas)[0])
            attr.append(obs["attr"])
            if done:
                break
            a = agent.actor.act(agent.features(h, z["fused"][-1][None]))
            obs, reward, term, trunc, _ = env.step(a[0].numpy())
            nxt.append(len(attr))  # the observation this step leads to
            r.append(reward)
            h, done = agent.wm.step(h, z["fused"][-1][None], a), term or trunc
    env.close()
    return {"z": {m: torch.stack(v) for m, v in z.items()}, "attr": np.array(attr), "next": nxt, "r": r}


def reward_transfer(paths: tuple[str, ...], episodes: int, steps: int = 3_000) -> dict:
    """Part 6: {reader: (|r_hat - r| on the training agents' steps, on the left-out agent's)}."""
    runs = [agent_episodes(p, episodes, seed=1000 * (i + 1)) for i, p in enumerate(paths)]
    every = np.concatenate([run["attr"] for run in runs])
    mean, std = every.mean(0), every.std(0) + 1e-3
    readers = {m: [run["z"][m] for run in runs] for m in runs[0]["z"]}
    readers["true attributes"] = [torch.as_tensor((run["attr"] - mean) / std).float() for run in runs]
    out = {}
    for name, xs in readers.items():
        pairs = [(x[run["next"]], torch.as_tensor(run["r"]).float()) for x, run in zip(xs, runs, strict=True)]
        errs = []
        for left in range(len(runs)):
            x = torch.cat([p[0] for i, p in enumerate(pairs) if i != left])
            y = torch.cat([p[1] for i, p in enumerate(pairs) if i != left])
            torch.manual_seed(0)
            head = G.mlp(x.shape[1], 256, 1, 2)
            opt = torch.optim.Adam(head.parameters(), 3e-4)
            with torch.enable_grad():  # main() runs without gradients
                for _ in range(steps):
                    j = torch.randint(0, len(y), (512,))
                    loss = (head(x[j]).squeeze(-1) - y[j]).pow(2).mean()
                    opt.zero_grad()
                    loss.backward()
                    opt.step()
            with torch.no_grad():
                fit = (head(x).squeeze(-1) - y).abs().mean().item()
                errs.append((fit, (head(pairs[left][0]).squeeze(-1) - pairs[left][1]).abs().mean().item()))
        out[name] = tuple(np.mean(errs, axis=0))
    return out


def decoded_end_effector(encoder, z: torch.Tensor) -> np.ndarray:
    """The end-effector position (m) that z broadcasts to the attributes: d_attr, then the attribute VAE's
    decoder, un-normalised (the end effector is attributes 18-20 of RoboDeskEnv.attributes)."""
    attr = encoder.vae_attr.decoder(encoder.gw.d["attr"](z)) * encoder.attr_std + encoder.attr_mean
    return attr[0, 18:21].numpy()


@torch.no_grad()
def windowed_state(wm, zs: list, actions: list, window: int) -> torch.Tensor:
    """Part 7: h after the last ``window`` of the (z, a) steps given, read from h = 0 (as the newest h_t of
    a replayed sequence)."""
    h = torch.zeros(zs[0].shape[0], wm.hidden)
    for z, a in zip(zs[-window:], actions[-window:], strict=True):
        h = wm.step(h, z, a)
    return h


@torch.no_grad()
def episode_spread(path: str, episodes: int, seed: int = 900) -> dict:
    """Part 7: {way: (normalised returns, start distances in cm, shares of steps at a joint limit)}, the
    N episodes of each way stepped side by side."""
    from envs.robodesk import RoboDeskEnv
    from envs.robodesk_experts import PLANS

    agent, encoder, env0 = agent_in_simulator(path)
    ck = read_checkpoint(path)
    args = G.Args(**{k: v for k, v in ck["args"].items() if k in G.Args.__dataclass_fields__}).resolve()
    ref = G.reference_returns(args)
    if ref is None:
        raise SystemExit(f"error: part 7 needs a task with a scripted expert; {args.task} has none")
    env0.close()
    ways = {"collected": (False, 0), "collected, h from the last steps": (False, args.batch_length)}
    ways["evaluation"] = (True, 0)
    out = {}
    for way, (mode, window) in ways.items():
        torch.manual_seed(seed)  # the two collected ways draw the same actions from the same states
        kw = {"render_quality": args.render_quality, "episode_length": args.episode_length}
        envs = [RoboDeskEnv(task=args.task, **kw) for _ in range(episodes)]
        obs = [e.reset(seed=seed + i)[0] for i, e in enumerate(envs)]
        lo, hi = envs[0].joint_bounds[:7].T
        # distance to the target, the task expert's last way-point
        ee = [e.data.site_xpos[e._ee_site] for e in envs]
        start = [100 * np.linalg.norm(x - PLANS[args.task](e)[-1][0]) for x, e in zip(ee, envs, strict=True)]
        h, zs, acts = torch.zeros(episodes, agent.wm.hidden), [], []
        ret, at_limit, done = np.zeros(episodes), np.zeros(episodes), False
        while not done:
            z = encoder({k: np.stack([o[k] for o in obs]) for k in obs[0]})
            if window and zs:
                h = windowed_state(agent.wm, zs, acts, window)
            a = agent.actor.act(agent.features(h, z), mode=mode)
            if not mode:
                a = G.explore(a, args, 0)
            if window:
                zs, acts = (zs + [z])[-window:], (acts + [a])[-window:]
            h = agent.wm.step(h, z, a)
            for i, e in enumerate(envs):
                obs[i], r, term, trunc, _ = e.step(a[i].numpy())
                ret[i] += r
                at_limit[i] += np.any(np.minimum(e.data.qpos[:7] - lo, hi - e.data.qpos[:7]) < 0.1)
                done = term or trunc
        steps = envs[0]._num_steps / G.ACTION_REPEAT["robodesk"]
        for e in envs:
            e.close()
        out[way] = ((ret - ref[0]) / (ref[1] - ref[0]), np.array(start), at_limit / steps)
    return out


def print_spread(spread: dict) -> None:
    """Part 7's lines: per way, the return's spread and what sets its failed episodes apart."""
    for way, (ret, start, at_limit) in spread.items():
        sem = ret.std(ddof=1) / np.sqrt(len(ret)) if len(ret) > 1 else 0.0
        bad = ret < 0
        line = f"  {way}: normalised return {ret.mean():.2f} ± {sem:.2f} over {len(ret)} episodes, "
        line += f"{bad.sum()} below 0 ({np.round(ret, 2)})"
        if bad.any() and not bad.all():
            line += (
                f"; those start {start[bad].mean():.0f} cm from the target (the others "
                f"{start[~bad].mean():.0f}) and have a joint within 0.1 rad of its bound in "
                f"{100 * at_limit[bad].mean():.0f}% of their steps (the others "
                f"{100 * at_limit[~bad].mean():.0f}%)"
            )
        print(line)


def discounted_returns(rewards: np.ndarray, v_end: float, gamma: float) -> np.ndarray:
    """G_t = r_t + gamma G_{t+1} over an episode's stored rewards (entry t's reward leads from state t to
    t + 1), G at the final observation = ``v_end``; one value per state, the final one included."""
    g = np.empty(len(rewards) + 1)
    g[-1] = v_end
    for t in range(len(rewards) - 1, -1, -1):
        g[t] = rewards[t] + gamma * g[t + 1]
    return g


# Part 8's groups by the reward of the step before (a button task, per agent step of 4 frames): the
# distance part is at most 0.75 x 4 = 3, the light adds up to 1.
REWARD_GROUPS = {"light on": (3.05, np.inf), "near, unpressed": (2.7, 3.05), "farther": (-np.inf, 2.7)}
BUTTON_TASKS = ("push_green", "push_red", "push_blue")


@torch.no_grad()
def critic_bias(
    agent, replay: dict, episodes: int, gamma: float, reward_offset: float = 0.0, task: str = "push_green"
) -> dict:
    """Part 8: {group: (states, mean V, mean G)} over the newest ``episodes`` whole episodes of the
    replay's first stream; h_t is filtered from h = 0 at each episode's start as when acting."""
    if task not in BUTTON_TASKS:
        raise SystemExit(
            f"error: part 8 groups a button task's rewards ({', '.join(BUTTON_TASKS)}), not {task}'s"
        )
    pos, count, cap = int(replay["pos"][0]), int(replay["count"][0]), replay["z"].shape[1]
    idx = np.arange(pos - min(count, cap), pos) % cap  # oldest to newest
    z, a = (torch.as_tensor(replay[k][0][idx]) for k in ("z", "a"))
    r, first, last = (np.asarray(replay[k][0][idx]) for k in ("r", "first", "last"))
    starts, ends = np.flatnonzero(first > 0), np.flatnonzero(last > 0)
    whole = [(s, ends[ends >= s][0]) for s in starts if (ends >= s).any()]
    values, returns, before = [], [], []
    for s, e in whole[-episodes:]:
        h, v = torch.zeros(1, agent.wm.hidden), []
        for t in range(s, e + 1):
            v.append(float(agent.twohot.mean(agent.critic(agent.features(h, z[t][None])))))
            h = agent.wm.step(h, z[t][None], a[t][None])
        g = discounted_returns(r[s:e] - reward_offset, v[-1], gamma)  # the rewards the critic learns
        values.append(np.array(v[:-1])), returns.append(g[:-1]), before.append(np.r_[np.nan, r[s : e - 1]])
    v, g, b = map(np.concatenate, (values, returns, before))
    out = {}
    for name, (lo, hi) in REWARD_GROUPS.items():
        m = (b > lo) & (b <= hi)
        out[name] = (
            int(m.sum()),
            float(v[m].mean()) if m.any() else np.nan,
            float(g[m].mean()) if m.any() else np.nan,
        )
    return out


# Part 9's tasks and the joint of the object each one opens.
OBJECT_JOINTS = {"open_slide": "slide_joint", "open_drawer": "drawer_joint"}


class UniformPolicy:
    """The normalised return's 0: actions drawn uniformly from [-1, 1]^5."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        pass

    def act(self, env, obs: dict) -> np.ndarray:
        return self.rng.uniform(-1, 1, 5)


class ExpertPolicy:
    """The normalised return's 1: the task's scripted expert, without action noise."""

    def __init__(self, env):
        from envs.robodesk_experts import EXPERTS

        self.expert = EXPERTS[env.task](env)

    def reset(self) -> None:
        self.expert.reset()

    def act(self, env, obs: dict) -> np.ndarray:
        return self.expert.act(env)


class AgentPolicy:
    """A checkpoint's agent acting as the run evaluates it: actions sampled, no exploration noise."""

    def __init__(self, agent, encoder):
        self.agent, self.encoder = agent, encoder

    def reset(self) -> None:
        self.h = torch.zeros(1, self.agent.wm.hidden)

    @torch.no_grad()
    def act(self, env, obs: dict) -> np.ndarray:
        z = self.encoder({k: v[None] for k, v in obs.items()})
        a = self.agent.actor.act(self.agent.features(self.h, z))
        self.h = self.agent.wm.step(self.h, z, a)
        return a[0].numpy()


def object_reach(env, policy, episodes: int, seed: int = 950) -> dict[str, np.ndarray]:
    """Part 9 for one policy: per episode the end effector's closest approach to the contact point (cm),
    the largest movement of the object's joint from its value at reset (cm) and the success count (agent
    steps in which the task's success test holds)."""
    from envs.robodesk_experts import PLANS

    if env.task not in OBJECT_JOINTS:
        raise SystemExit(f"error: part 9 reads an object task ({', '.join(OBJECT_JOINTS)}), not {env.task}")
    joint = OBJECT_JOINTS[env.task]
    out = {k: np.zeros(episodes) for k in ("closest", "moved", "success")}
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        policy.reset()
        start, dists, done = float(env._qpos(joint)[0]), [], False
        while not done:
            contact = PLANS[env.task](env)[-2][0]  # where the expert starts to push or pull; moves with it
            dists.append(np.linalg.norm(env.data.site_xpos[env._ee_site] - contact))
            obs, _, term, trunc, info = env.step(policy.act(env, obs))
            out["moved"][ep] = max(out["moved"][ep], 100 * abs(float(env._qpos(joint)[0]) - start))
            out["success"][ep] += info["success"]
            done = term or trunc
        out["closest"][ep] = 100 * min(dists)
    return out


def object_reaches(path: str, episodes: int) -> dict[str, dict[str, np.ndarray]]:
    """Part 9: ``object_reach`` of the checkpoint's agent, the random policy and the scripted expert."""
    from envs.robodesk import RoboDeskEnv

    agent, encoder, env = agent_in_simulator(path)
    # The random policy and the expert read no image: their env renders none (the same physics).
    blind = RoboDeskEnv(task=env.task, render_images=False, episode_length=env.episode_length)
    out = {"agent": object_reach(env, AgentPolicy(agent, encoder), episodes)}
    out |= {
        name: object_reach(blind, p, episodes)
        for name, p in (("random", UniformPolicy(0)), ("expert", ExpertPolicy(blind)))
    }
    env.close()
    blind.close()
    return out


def press_tolerance() -> None:
    """The scripted push_green expert with its target moved off the button's centre, at four gripper
    settings: the share of steps 60-120 with the light on (the press has settled by step 60)."""
    import gymnasium as gym

    from envs.robodesk_experts import WaypointExpert

    env = gym.make("RoboDesk-v0", task="push_green", render_quality="fast")
    for grip in (-1.0, -0.3, 0.0, 0.3, 1.0):
        shares = []
        for dx, dy in ((0, 0), (0.02, 0), (0.04, 0), (0.06, 0), (0, 0.02), (0, 0.04)):

            def plan(e, dx=dx, dy=dy, grip=grip):
                b = e._xpos("green_button") + [dx, dy, 0.0]
                return [(b + [0, 0, 0.12], grip, 0.02), (b + [0, 0, 0.035], grip, 0.0)]

            expert, _ = WaypointExpert(env, plan), env.reset(seed=10_000)
            on = [env.step(expert.act(env))[4]["success"] for _ in range(120)]
            shares.append(f"({100 * dx:.0f}, {100 * dy:.0f}) cm {np.mean(on[60:]):.2f}")
        print(f"  expert, gripper action {grip:+.1f}, light on at offset " + ", ".join(shares))
    env.close()


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
            "  x/y/z actions reversed from one step to the next, per 10,000 frames (%): "
            + " ".join(f"{100 * x:.0f}" for x in r["reversals"])
        )
        for frame, r2, resid in r["predictability"]:
            print(
                f"  stored actions from frame {frame:,}: R^2 from (z_t, a_t-1) {np.round(r2, 2)}, "
                f"unexplained std {np.round(resid, 2)}"
            )
        print(
            f"  rewards ({r['sequences']} sequences, real mean {r['reward_mean']:.2f} per agent step): "
            f"|r_hat - r| at horizons 1/5/10/20 one step ahead {np.round(r['one_step_err'], 3)}, open loop "
            f"{np.round(r['open_loop_err'], 3)}; 20-step sums correlate {r['return_corr']:.3f} (open loop)"
        )
        print(
            f"  one step ahead at the {r['onsets']} reward jumps > 0.5 of the newest 20,000 entries "
            f"(push_green: the light comes on): real {r['onset_real']:.2f} after {r['onset_before']:.2f}, "
            f"predicted {r['onset_pred']:.2f}; elsewhere |r_hat - r| {r['rest_err']:.3f}"
        )
        if args.counterfactual_states:
            c = counterfactual_actions(path, args.counterfactual_states)
            print(
                f"  other actions ({args.counterfactual_states} states): rank correlation of the 7 actions' "
                f"5-step rewards, simulator against dream, {c['rank_corr']:.2f} ± {c['rank_corr_sem']:.2f} "
                f"(s.e.m.); spread across them {c['spread_true']:.2f} true, {c['spread_dream']:.2f} dreamt"
            )
            r |= c
        if args.press_episodes:
            p = pressing(path, args.press_episodes)
            print(
                f"  pressing ({args.press_episodes} episodes): light on in {100 * p['pressed']:.0f}% of the "
                f"steps, reward {p['reward']:.2f} per agent step, {100 * p['near']:.0f}% of the steps within "
                "8 cm of the button; within 4 cm, gripper action closed / mid / open in "
                + " / ".join(f"{100 * p['share_' + g]:.0f}%" for g in GRIP)
                + " of the steps, light on there in "
                + " / ".join(f"{100 * p['pressed_' + g]:.0f}%" for g in GRIP)
                + f"; closed there, the end effector's median height above the button {p['height_on']:.1f} "
                f"cm with the light on, {p['height_off']:.1f} cm with it off, mean x, y offset "
                f"{np.round(p['offset_on'], 1)} and {np.round(p['offset_off'], 1)} cm"
            )
            if "probes" in p:
                print(
                    f"  from {p['probes']} states within 4 cm with the light off, 10 agent steps of 'down "
                    f"with the gripper closed' / 'still': true reward {np.round(p['probe_true'], 1)}, dreamt "
                    f"{np.round(p['probe_dream'], 1)}; light on in {100 * p['probe_light']:.0f}% of the "
                    "steps going down"
                )
                print(
                    "  going down, reward at steps 1-10: true "
                    f"{np.round(p['probe_steps_true'], 2)}, dreamt {np.round(p['probe_steps_dream'], 2)}; "
                    f"end effector moved |x|, |y|, z (cm, mean over states): true "
                    f"{np.round(p['probe_moved_true'], 1)}, dreamt {np.round(p['probe_moved_dream'], 1)}"
                )
            r |= p
        if args.gw_coverage:
            cov, agent_attr, encoders = gw_coverage(path, args.gw_coverage, args.gw_dirs)
            for (g, policy, m), (err, err_near, corr) in cov.items():
                print(
                    f"  {g}, {policy} episodes, z from {m}: end effector {err:.1f} cm ({err_near:.1f} within "
                    f"15 cm of the button), light read-out correlation {corr:.3f}"
                )
            r["gw_coverage"] = cov
            if args.coverage_data:
                near = joint_coverage(agent_attr, args.coverage_data)
                print(
                    f"  robot joint configurations, median distance (data std units) to the nearest of each "
                    f"source in {args.coverage_data}, the agent's (the source's held-out episodes'): "
                    + ", ".join(f"{k} {a:.2f} ({h:.2f})" for k, (a, h) in near.items())
                )
                r["joint_coverage"] = near
                shares = pose_shares(agent_attr, args.coverage_data)
                for pose in POSES:
                    print(
                        f"  share of steps with {pose}: "
                        + ", ".join(f"{g} {v[pose]:.3f}" for g, v in shares.items())
                    )
                r["pose_shares"] = shares
                held = held_out_by_source(encoders, args.coverage_data)
                for (g, src, m), err in held.items():
                    print(
                        f"  {g}, held-out {src} samples of {args.coverage_data}, z from {m}: end effector "
                        f"{err:.1f} cm"
                    )
                r["held_out_by_source"] = held
        if args.spread_episodes:
            r["spread"] = episode_spread(path, args.spread_episodes)
            print_spread(r["spread"])
        if args.critic_bias:
            ck = read_checkpoint(path)
            agent, run_args = replay_agent(ck)
            r["critic_bias"] = critic_bias(
                agent, ck["replay"], args.critic_bias, run_args.gamma, run_args.reward_offset, run_args.task
            )
            print(
                f"  critic on the newest {args.critic_bias} replayed episodes, V against the real discounted "
                "return G, by the reward of the step before: "
                + "; ".join(
                    f"{k} ({n} states) V {v:.1f}, G {g:.1f}, V - G {v - g:+.1f}"
                    for k, (n, v, g) in r["critic_bias"].items()
                )
            )
        if args.object_episodes:
            r["object_reach"] = object_reaches(path, args.object_episodes)
            for name, o in r["object_reach"].items():
                print(
                    f"  {name}, {args.object_episodes} episodes: closest to the contact point "
                    f"{np.median(o['closest']):.1f} cm (median; each {np.round(o['closest'], 1)}); the "
                    f"object moved at most {np.round(o['moved'], 1)} cm; success count "
                    f"{np.round(o['success'])}"
                )
        out.append(r)
    if args.reward_transfer:
        if len(args.checkpoints) < 2:
            raise SystemExit("--reward-transfer needs two checkpoints or more (one is left out in turn)")
        for name, (fit, left) in reward_transfer(args.checkpoints, args.reward_transfer).items():
            print(
                f"reward from the next {name}: |r_hat - r| {fit:.3f} on the agents fit, {left:.3f} on the "
                "one left out"
            )
    if args.press_tolerance:
        press_tolerance()
    return out


if __name__ == "__main__":
    main(tyro.cli(Args))
