"""Does the open-loop world-model loss (gw_dreamer_experiments.py --wm-open-loop K) make RoboDesk dreams
follow the simulator for longer? Offline, on data the agents collected: the world model of one run's
checkpoint is trained further on that run's replay, once with gw_dreamer.py's one-step loss and once per
K with the open-loop term added (same batches, same number of updates), then each is run open loop along
another run's replayed actions (held-out data) and compared with what really happened.

Printed per world model: mean |r_hat - r| at open-loop steps 1, 5, 10 and 20; the z error (squared, summed
over z's 76 dimensions) at the same steps; the end effector that the dreamt z decodes to through the GW,
its distance (cm) from the one the real z decodes to; and, from the held-out states where the green light
is on (the reward of a press), the dreamt against the real reward summed over the next 10 steps.

    python benchmarks/experiments/wm_open_loop_offline.py RUN.pt --updates 600 --k 0 10
    python benchmarks/experiments/wm_open_loop_offline.py RUN.pt --heldout OTHER_RUN.pt
    python benchmarks/experiments/wm_open_loop_offline.py RUN.pt --heldout OTHER_RUN.pt --by-age
    python benchmarks/experiments/wm_open_loop_offline.py RUN.pt --heldout LATER.pt --fresh --wm-residual

--by-age trains nothing: each of the two checkpoints' world models reads each run's whole replay (first
stream) one step ahead, the real z given at every step as when acting, and prints its z error and
end-effector error by the entries' age (the first 250 agent steps are the random policy's), and in brackets
the end-effector error of predicting that the hand does not move.
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro
from tyro.conf import Positional

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gw_dreamer_experiments as X  # noqa: E402

G = X.G  # gw_dreamer.py


@dataclass
class Args:
    train: Positional[str]
    """a gw_dreamer.py RoboDesk agent checkpoint: its world model is the start, its replay the data"""
    heldout: str | None = None
    """another run's checkpoint whose replay is the held-out data; by default the held-out data are the
    --newest entries of the training run's own replay, left out of the training"""
    newest: int = 3000
    """without --heldout: the newest entries of the training replay held out (the agent's next data)"""
    heldout_newest: int = 0
    """with --heldout: windows from its newest entries only (0: anywhere in it); with a later checkpoint of
    the same run, the data the training checkpoint's agent collected next"""
    k: tuple[int, ...] = (0, 10)
    """open-loop horizons to compare (0: the one-step loss alone)"""
    updates: int = 1500
    """world-model updates of each variant"""
    stride: int = 8
    """--wm-open-loop-stride"""
    recent_fraction: float = 0.0
    """--recent-fraction of the training batches"""
    recent_window: int = 5000
    """--recent-window"""
    wm_residual: bool = False
    """--wm-residual (the z head predicts a change of z; with --fresh)"""
    fresh: bool = False
    """start from a freshly initialised world model instead of the checkpoint's"""
    windows: int = 512
    """held-out windows (64 warm-up steps, then 20 open-loop steps)"""
    seed: int = 0
    torch_threads: int = 1
    by_age: bool = False
    """print the one-step errors of both checkpoints' world models on both replays by age, then stop"""


def load(path: str):
    ck = torch.load(path, weights_only=False, map_location="cpu")
    if ck.get("kind") != "gw_dreamer" or ck.get("env") != "robodesk":
        raise SystemExit(f"error: {path} is not a gw_dreamer.py RoboDesk agent checkpoint")
    fields = X.Args.__dataclass_fields__
    args = X.Args(**{k: v for k, v in ck["args"].items() if k in fields}).resolve()
    return ck, args


def replay_of(ck: dict, args, seed: int, leave_out: int = 0) -> G.Replay:
    """The run's replay, without its newest ``leave_out`` entries (a buffer that has not wrapped), sampled
    as --recent-fraction asks."""
    z_dim = ck["replay"]["z"].shape[-1]
    X.RecentReplay.fraction, X.RecentReplay.window = args.recent_fraction, args.recent_window
    replay = X.RecentReplay(args.buffer_size, args.num_envs, z_dim, G.SIZES["robodesk"]["actions"], seed)
    state = dict(ck["replay"])
    if leave_out:
        if (state["count"] >= replay.cap).any():
            raise SystemExit("error: --newest needs a replay that has not wrapped; give --heldout")
        state["count"] = state["count"] - leave_out
        state["pos"] = state["count"].copy()
        state["last"] = state["last"].copy()
        state["last"][np.arange(len(state["pos"])), state["pos"] - 1] = (
            1.0  # no transition into left-out data
        )
    replay.load_state_dict(state | {"rng": np.random.default_rng(seed).bit_generator.state})
    return replay


def train(agent, replay: G.Replay, args, updates: int) -> float:
    """``updates`` world-model updates as train_update makes them; seconds per update."""
    opt = torch.optim.Adam(agent.wm.parameters(), lr=args.wm_lr, eps=1e-8)
    start = time.perf_counter()
    for _ in range(updates):
        batch = {k: torch.as_tensor(v) for k, v in replay.sample(args.batch_size, args.batch_length).items()}
        loss, *_ = G.world_model_loss_open_loop(agent.wm, agent.reward_dec, batch, args)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(agent.wm.parameters(), 1000.0)
        opt.step()
    return (time.perf_counter() - start) / max(updates, 1)


def heldout_windows(ck: dict, n: int, seed: int, newest: int = 0, warm: int = 64, horizon: int = 20) -> dict:
    """Windows in the replay's streams (in their ``newest`` entries when given) inside one episode."""
    rep, out = ck["replay"], {"z": [], "a": [], "r": []}
    rng = np.random.default_rng(seed)
    for _ in range(20 * n):
        i = rng.integers(len(rep["count"]))
        count = min(int(rep["count"][i]), rep["z"].shape[1])
        s = rng.integers(count - newest if newest else 0, count - warm - horizon - 1)
        if rep["first"][i, s + 1 : s + warm + horizon + 1].any():
            continue
        for key in out:
            out[key].append(rep[key][i, s : s + warm + horizon + 1])
        if len(out["z"]) == n:
            break
    return {k: torch.as_tensor(np.stack(v)) for k, v in out.items()}


@torch.no_grad()
def evaluate(agent, encoder, w: dict, reward_offset: float, warm: int = 64, horizon: int = 20) -> dict:
    wm, z, a, r = agent.wm, w["z"], w["a"], w["r"] - reward_offset
    h = torch.zeros(len(z), wm.hidden)
    for t in range(warm):
        h = wm.step(h, z[:, t], a[:, t])
    z_open, r_err, z_err, ee_err, dreamt = z[:, warm], [], [], [], []
    for k in range(horizon):
        t = warm + k
        h = wm.step(h, z_open, a[:, t])
        z_open, r_out, _ = wm.heads(h)
        r_hat = agent.reward_dec.value(r_out)
        dreamt.append(r_hat)
        r_err.append((r_hat - r[:, t]).abs().mean())
        z_err.append(((z_open - z[:, t + 1]) ** 2).sum(-1).mean())
        ee_err.append(
            100 * (end_effector(encoder, z_open) - end_effector(encoder, z[:, t + 1])).norm(dim=-1).mean()
        )
    dreamt = torch.stack(dreamt, 1)
    # The light is on: the reward of the last warm-up step is a press's (hovering alone earns < 3.3).
    pressed = r[:, warm - 1] + reward_offset > 3.3
    at = [0, 4, 9, horizon - 1]
    return {
        "r_err": [float(r_err[i]) for i in at],
        "z_err": [float(z_err[i]) for i in at],
        "ee_cm": [float(ee_err[i]) for i in at],
        "pressed": int(pressed.sum()),
        "press_dreamt": float(dreamt[pressed, :10].sum(1).mean() + 10 * reward_offset)
        if pressed.any()
        else np.nan,
        "press_real": float(r[pressed, warm : warm + 10].sum(1).mean() + 10 * reward_offset)
        if pressed.any()
        else np.nan,
    }


@torch.no_grad()
def one_step_by_age(
    ck_model: dict, ck_data: dict, encoder, bounds=(0, 250, 2500, 10000, 20000, 30000)
) -> str:
    """One-step z error (summed over z) / end-effector error (cm) of ``ck_model``'s world model along the
    first stream of ``ck_data``'s replay, by the entries' position in it."""
    done_head = any(k.startswith("wm.done_head.") for k in ck_model["agent"])
    agent = G.Agent("robodesk", encoder.z_dim, "twohot", 0.99, True, done_head)
    agent.load_state_dict(ck_model["agent"])
    rep = ck_data["replay"]
    n = min(int(rep["count"][0]), rep["z"].shape[1])
    z, a = torch.as_tensor(rep["z"][0, :n]), torch.as_tensor(rep["a"][0, :n])
    first, last = rep["first"][0, :n], rep["last"][0, :n]
    h, hs = torch.zeros(1, agent.wm.hidden), []
    for t in range(n - 1):
        h = h * (1 - float(first[t]))
        h = agent.wm.step(h, z[t : t + 1], a[t : t + 1])
        hs.append(h)
    z_hat = agent.wm.heads(torch.cat(hs))[0]
    err_z = ((z_hat - z[1:]) ** 2).sum(-1).numpy()
    ee = end_effector(encoder, z)
    err_ee = (100 * (end_effector(encoder, z_hat) - ee[1:]).norm(dim=-1)).numpy()
    still = (100 * (ee[:-1] - ee[1:]).norm(dim=-1)).numpy()  # the hand predicted not to move
    keep = last[:-1] == 0  # no transition out of an episode's final observation
    edges = [b for b in bounds if b < n - 1] + [n - 1]
    cells = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = keep[lo:hi]
        z_, ee_, still_ = (x[lo:hi][m].mean() for x in (err_z, err_ee, still))
        cells.append(f"[{lo:,}, {hi:,}) {z_:.3f} / {ee_:.2f} ({still_:.2f})")
    return "; ".join(cells)


def end_effector(encoder, z: torch.Tensor) -> torch.Tensor:
    """The end-effector position (m) z broadcasts to the attributes (attributes 18-20)."""
    attr = encoder.vae_attr.decoder(encoder.gw.d["attr"](z)) * encoder.attr_std + encoder.attr_mean
    return attr[:, 18:21]


def main(a: Args) -> None:
    if a.wm_residual and not a.fresh:
        raise SystemExit("error: --wm-residual trains a fresh world model; give --fresh")
    torch.set_num_threads(a.torch_threads)
    ck, run_args = load(a.train)
    held = load(a.heldout)[0] if a.heldout else ck
    if a.by_age:
        encoder, _ = G.load_frozen(run_args, torch.device("cpu"))
        names = {a.train: ck} | ({a.heldout: held} if a.heldout else {})
        for model_name, model in names.items():
            for data_name, data in names.items():
                print(f"world model of {model_name} on the replay of {data_name}:")
                print(
                    "  z error / end effector cm (not moving: cm) by age:",
                    one_step_by_age(model, data, encoder),
                )
        return
    leave_out = 0 if a.heldout else a.newest
    encoder, _ = G.load_frozen(run_args, torch.device("cpu"))
    windows = heldout_windows(held, a.windows, a.seed, a.heldout_newest if a.heldout else leave_out)
    pressed = int((windows["r"][:, 63] > 3.3).sum())
    where = f"its newest {a.newest:,} entries" if not a.heldout else a.heldout
    where += f" (its newest {a.heldout_newest:,} entries)" if a.heldout and a.heldout_newest else ""
    print(f"train replay {a.train}; held out: {len(windows['z'])} windows of {where} ({pressed} pressed)")
    for k in a.k:
        torch.manual_seed(a.seed)
        args = X.Args(
            **vars(run_args)
            | {"wm_open_loop": k, "wm_open_loop_stride": a.stride, "wm_residual": a.wm_residual}
            | {"recent_fraction": a.recent_fraction, "recent_window": a.recent_window}
        )
        agent = X.experiment_agent(args)(
            "robodesk", encoder.z_dim, run_args.reward_loss, run_args.return_norm_decay, True
        )
        if not a.fresh:
            agent.load_state_dict(ck["agent"])
        if k == a.k[0]:
            print("before:", fmt(evaluate(agent, encoder, windows, args.reward_offset)))
        s = train(agent, replay_of(ck, args, a.seed, leave_out), args, a.updates)
        print(
            f"K={k:2d} ({a.updates} updates, {s:.3f} s each):",
            fmt(evaluate(agent, encoder, windows, args.reward_offset)),
        )


def fmt(e: dict) -> str:
    f = lambda xs: " / ".join(f"{x:.3f}" for x in xs)  # noqa: E731
    return (
        f"|r err| at 1/5/10/20 {f(e['r_err'])}; z err {f(e['z_err'])}; end effector {f(e['ee_cm'])} cm; "
        f"10 steps from a press: dreamt {e['press_dreamt']:.1f}, real {e['press_real']:.1f} ({e['pressed']})"
    )


if __name__ == "__main__":
    main(tyro.cli(Args))
