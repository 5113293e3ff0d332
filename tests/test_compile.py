"""--compile: the update through torch.compile computes what the eager update computes. Two copies of an
agent, one updated eagerly and one with the compiled losses, from the same replayed batch and the same
random numbers (inductor draws them as eager does with ``fallback_random``), end with the same losses
and the same weights, within float tolerance (the compiled kernels sum in another order)."""

import copy

import numpy as np
import pytest
import torch
from torch._inductor import config as inductor_config

import dreamer_baseline as D
import gw_dreamer as G
import gw_dreamer_e2e as E

SMALL = dict(batch_size=3, batch_length=4, imag_horizon=3)


def gw_case():
    args = G.Args(**SMALL).resolve()
    agent = G.Agent("simple_shapes", 10, "twohot")
    replay = G.Replay(200, 1, 10, 7, 0)
    rng = np.random.default_rng(0)
    for t in range(40):
        replay.add(
            [0], rng.uniform(-1, 1, (1, 10)), np.eye(7)[[t % 7]], [-float(t % 5)], [0], [t % 17 == 0], [0]
        )
    return G, agent, replay, args


def e2e_case():
    args = E.Args(**SMALL, gw_batch_size=16).resolve()
    agent = E.Agent("simple_shapes", "twohot")
    replay = E.Replay(200, 1, 10, 7, 0)
    rng = np.random.default_rng(0)
    for t in range(40):
        u = rng.normal(size=(2, 1, 10))
        replay.add([0], u[0], u[1], np.eye(7)[[t % 7]], [-float(t % 5)], [0], [t % 17 == 0], [0])
    return E, agent, replay, args


def dreamer_case():
    args = D.Args(**SMALL, deter=16, hidden=8, units=8, cnn_depth=2, classes=4).resolve()
    spaces = D.Observer("simple_shapes", "raw", None).spaces("simple_shapes")
    agent = D.Agent("simple_shapes", spaces, args)
    replay = D.Replay(200, 1, spaces, agent.n_actions, 0)
    rng = np.random.default_rng(0)
    for t in range(40):
        entry = {"image": rng.integers(0, 256, (1, *spaces["image"])).astype(np.uint8)}
        entry |= {"attr": rng.normal(size=(1, *spaces["attr"])), "action": np.eye(7)[[t % 7]]}
        entry |= {"reward": [-float(t % 5)], "terminal": [0.0], "first": [float(t % 17 == 0)]}
        replay.add(np.array([0]), entry)
    return D, agent, replay, args


# gw_dreamer.py through the whole compiler (inductor's generated kernels); the other two through its
# graph capture alone ("aot_eager": what dynamo and AOT autograd make of the update, where the mistakes
# this test found were), which compiles in seconds instead of minutes.
CASES = [(gw_case, "inductor"), (e2e_case, "aot_eager"), (dreamer_case, "aot_eager")]


@pytest.mark.parametrize(("case", "backend"), CASES, ids=["gw_dreamer", "e2e", "dreamer"])
def test_compiled_update_matches_the_eager_one(case, backend, monkeypatch):
    monkeypatch.setattr(inductor_config, "fallback_random", True)
    torch.manual_seed(0)
    mod, agent, replay, args = case()
    twin, replay_twin, initial = (
        copy.deepcopy(agent),
        copy.deepcopy(replay),
        copy.deepcopy(agent.state_dict()),
    )
    logs = {}
    for name, net, rep, losses in (
        ("eager", agent, replay, mod.EAGER),
        ("compiled", twin, replay_twin, None),
    ):
        losses = losses or mod.compiled_losses("cpu", backend)
        opts = mod.make_optimizers(net, args)
        torch.manual_seed(1)
        logs[name] = [mod.train_update(net, opts, rep, args, losses=losses) for _ in range(2)]
    for a, b in zip(logs["eager"], logs["compiled"], strict=True):
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-5, msg=k)
    for (k, p), q in zip(agent.state_dict().items(), twin.state_dict().values(), strict=True):
        torch.testing.assert_close(p, q, rtol=1e-4, atol=1e-5, msg=k)
    assert any(not torch.equal(p, initial[k]) for k, p in agent.state_dict().items())  # the updates did train
