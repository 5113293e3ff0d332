"""--stop-at-criterion of the three Dreamer-family agents: the run ends at the env step where the return
criterion is reached, and goes on without the flag. (ppo_variants.py, which stops after a whole rollout,
is tested in test_ppo_variants.py.)"""

import pytest
from conftest import DREAMER_SMALL, tiny_agent_args

import dreamer_baseline as D
import gw_dreamer as G
import gw_dreamer_e2e as E

SMALL = {
    G: dict(imag_horizon=5, train_ratio=10.0),
    E: dict(imag_horizon=5, train_ratio=10.0, gw_batch_size=64),
    D: DREAMER_SMALL | dict(train_ratio=1.0),
}


@pytest.mark.parametrize("module", [G, E, D], ids=["gw_dreamer", "gw_dreamer_e2e", "dreamer_baseline"])
def test_stop_at_criterion_ends_the_run_at_the_criterion(module, pretrained, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # its runs/ folder
    # every policy meets a criterion of -100 (normalised): it is reached at the 3rd episode's end
    small = SMALL[module] | dict(eval_episodes=1, video_every=0, seed=7, criterion=-100.0, smoothing=3)
    args = tiny_agent_args(module, pretrained, total_steps=50_000, stop_at_criterion=True, **small)
    out = module.main(args)
    assert out["criterion_step"] is not None and out["env_steps"] == out["criterion_step"] < 50_000
    again = tiny_agent_args(module, pretrained, total_steps=out["env_steps"] + 100, overwrite=True, **small)
    out = module.main(again)
    assert out["criterion_step"] < out["env_steps"]  # without the flag the run goes on
