"""A tanh-normal actor that acts by a draw from its own policy (``trainer.eval_actor=sample``).

The evaluator and the exported pilot fly an actor's mean action by default (the tanh of the
Gaussian mean). A learned actor trained through the safety filter can press against a building
with the mean and stay there: the filter holds it, the next state is the same, and so is the
next mean (``make pilot-stalls``). A draw from the policy it was trained with moves it off that
fixed point. This module flies that draw reproducibly: the noise comes from the module's own
generator, seeded with the evaluation seed and restarted at each flight, one ``[B, act_dim]``
standard-normal draw a step, so ``uavlae.fly`` (which draws the same stream for the exported
pilot) reproduces the evaluator's numbers.

    action = low + (high - low) · (tanh(loc + scale · ε) + 1) / 2,   ε ~ N(0, I)

which is the actor's own ``TanhNormal`` draw; ε = 0 is the mean action.
"""

from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.modules import ProbabilisticActor, TanhNormal

from uavlae.errors import ConfigError
from uavlae.policies.draws import draw, noise_stream, squash

EVAL_ACTORS = ("mean", "sample")


class SampledActor(TensorDictModuleBase):
    """``actor`` (a :class:`~torchrl.modules.ProbabilisticActor` with a ``TanhNormal`` head) acting
    by a draw from its policy, from a stream seeded with ``seed`` (:meth:`reset` restarts it)."""

    def __init__(self, actor: Any, seed: int):
        super().__init__()
        if not isinstance(actor, ProbabilisticActor):
            raise ConfigError(f"trainer.eval_actor=sample draws from a tanh-normal policy; this learner's actor is a "
                              f"{type(actor).__name__} (deterministic): use trainer.eval_actor=mean")
        self.actor = actor
        self.seed = int(seed)
        self.generator = noise_stream(self.seed)
        self.in_keys = list(actor.in_keys)
        self.out_keys = ["action"]

    def reset(self) -> None:
        """Restart the noise stream: each flight draws the same noise."""
        self.generator = noise_stream(self.seed)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        dist = self.actor.get_dist(td)  # writes the head's loc and scale into td
        if not isinstance(dist, TanhNormal):
            raise ConfigError(f"trainer.eval_actor=sample draws from a tanh-normal policy; this actor's head is "
                              f"{type(dist).__name__}: use trainer.eval_actor=mean")
        loc, scale = td.get("loc"), td.get("scale")
        flat = loc.reshape(-1, loc.shape[-1])
        noise = draw(self.generator, flat.shape[0], flat.shape[-1]).to(loc.device, loc.dtype).reshape(loc.shape)
        low, high = dist.low.to(loc.dtype), dist.high.to(loc.dtype)
        td.set("action", squash(loc, scale, noise, low, high))
        return td


def eval_actor(actor: Any, mode: str, seed: int) -> Any:
    """What an evaluation flies of a learner's ``actor``: itself (its mean action, the evaluator's
    deterministic exploration) or a :class:`SampledActor` seeded with ``seed``."""
    if mode not in EVAL_ACTORS:
        raise ConfigError(f"trainer.eval_actor={mode!r}: use one of {', '.join(EVAL_ACTORS)}")
    return actor if mode == "mean" else SampledActor(actor, seed)
