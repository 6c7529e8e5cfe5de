"""A deployed actor acting by a draw from its policy (trainer.eval_actor=sample,
uavlae/policies/sampling.py) on a hand-set network whose draws are worked out by hand, and the
refusals of an actor with no policy to draw from."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from uavlae.errors import ConfigError
from uavlae.policies.draws import draw, noise_stream
from uavlae.policies.networks import make_ddpg_actor, make_sac_actor
from uavlae.policies.sampling import SampledActor, eval_actor

BOX = Bounded(-torch.ones(2), torch.ones(2), shape=(2,))


def _hand_set_actor():
    """A SAC actor whose head ignores the observation: loc = (atanh 0.5, 0) and a zero scale
    input, which the biased softplus maps to scale 1 (SCALE_AT_ZERO)."""
    actor = make_sac_actor(3, BOX)
    last = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([math.atanh(0.5), 0.0, 0.0, 0.0]))
    return actor


def _obs(rows: int = 2) -> TensorDict:
    return TensorDict({"observation": torch.randn(rows, 3)}, batch_size=[rows])


def test_the_noise_stream_by_hand():
    """Seed 7's first two draws, written down once: the stream the evaluator and uavlae.fly share."""
    g = noise_stream(7)
    torch.testing.assert_close(draw(g, 2, 2), torch.tensor([[-0.1467951, 0.7861413], [0.9468216, -1.1143440]]))
    torch.testing.assert_close(draw(g, 2, 2), torch.tensor([[1.6907902, -0.8948279], [-0.3556250, 1.2323858]]))


def test_sampled_actor_draws_the_tanh_normal_action_by_hand():
    """action = tanh(loc + scale * eps): row 0 of the first step is (tanh(0.549306 - 0.146795),
    tanh(0 + 0.786141)) = (0.382095, 0.656218); the mean is (0.5, 0); a reset draws the same again."""
    actor = _hand_set_actor()
    sampled = eval_actor(actor, "sample", seed=7)
    assert isinstance(sampled, SampledActor) and eval_actor(actor, "mean", seed=7) is actor
    with torch.no_grad():
        first = sampled(_obs())["action"]
        second = sampled(_obs())["action"]
        sampled.reset()
        again = sampled(_obs())["action"]
    torch.testing.assert_close(first[0], torch.tensor([0.382095, 0.656218]), atol=1e-5, rtol=0)
    # row 1: (tanh(0.549306 + 0.946822), tanh(-1.114344)) = (0.904446, -0.805593)
    torch.testing.assert_close(first[1], torch.tensor([0.904446, -0.805593]), atol=1e-5, rtol=0)
    # the second step's row 0: (tanh(0.549306 + 1.690790), tanh(-0.894828)) = (0.977591, -0.713770)
    torch.testing.assert_close(second[0], torch.tensor([0.977591, -0.713770]), atol=1e-5, rtol=0)
    torch.testing.assert_close(again, first)


def test_an_actor_without_a_policy_is_refused():
    ddpg = make_ddpg_actor(3, BOX)
    with pytest.raises(ConfigError, match=r"\(deterministic\): use trainer.eval_actor=mean"):
        eval_actor(ddpg, "sample", seed=0)
    with pytest.raises(ConfigError, match="use one of mean, sample"):
        eval_actor(_hand_set_actor(), "noisy", seed=0)


def test_exporting_a_deterministic_actor_to_fly_by_draws_is_refused_and_writes_nothing(tmp_path):
    """uavlae.export applies the evaluator's check: a DDPG checkpoint exported as a pilot that
    acts by draws is refused with the evaluator's message, and no pilot file is left behind."""
    from omegaconf import OmegaConf

    from tests.test_train import _cfg
    from uavlae.checkpoint import save_checkpoint
    from uavlae.envs import make_env_config
    from uavlae.export import export_checkpoint
    from uavlae.factories import make_env, make_learner

    cfg = _cfg("+exp=ddpg", "safety_filter.mode=deploy")
    learner = make_learner(cfg.algo, make_env(make_env_config(cfg.env), 1, seed=0))
    save_checkpoint({"config": OmegaConf.to_container(cfg, resolve=True), "learner": learner.state_dict(),
                     "counters": {"frames": 0}}, tmp_path / "run")
    out = tmp_path / "pilot.pt2"
    with pytest.raises(ConfigError, match=r"\(deterministic\): use trainer.eval_actor=mean"):
        export_checkpoint(tmp_path / "run", out, actor_mode="sample")
    assert not out.exists()


def test_the_evaluation_with_an_advisor_flies_the_actor_as_the_evaluation_without():
    """OverridePolicy.advised(actor=...): the rows the advisor leaves to the actor act by the
    evaluation's own actor. Two rows, 2 m and 50 m from a building, d_th 20 m: row 0 is the
    advisor's (1, 1); row 1 is the actor's, by seed 7's draw (tanh(0.549306 + 0.946822),
    tanh(-1.114344)) = (0.904446, -0.805593), or without actor= its mean (0.5, 0)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from tests.test_advice import FixedAdvisor, _rows
    from uavlae.policies.override import OverridePolicy

    actor = _hand_set_actor()
    pol = OverridePolicy(actor, FixedAdvisor([1.0, 1.0]), mode="proximity", d_th=20.0)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        with pol.advised(actor=eval_actor(actor, "sample", seed=7)):
            drawn = pol(_rows([2.0, 50.0]))["action"]
        with pol.advised():
            mean = pol(_rows([2.0, 50.0]))["action"]
    torch.testing.assert_close(drawn, torch.tensor([[1.0, 1.0], [0.904446, -0.805593]]), atol=1e-5, rtol=0)
    torch.testing.assert_close(mean, torch.tensor([[1.0, 1.0], [0.5, 0.0]]), atol=1e-5, rtol=0)
    assert pol._eval_actor is None and "_eval_actor" not in dict(pol.named_children())
