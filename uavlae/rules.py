"""The rules of meaning a run's config must meet, beyond each value's type and range: settings that
each pass their own check but together make a metric undefined, a world unplayable or a method
something other than it says. Checked before a command writes anything, each broken rule one line
that names its keys, their values and what would be accepted (docs/model.md, "Rules a run's
config must meet", lists them with the ones the config models enforce on their own).

The world's rules are a run's, not the env config's: the physics and the scenario sampler accept
a world without GEs (the geometry tests use one), but a run on it measures nothing.
"""

from __future__ import annotations

from typing import Any

import torch

from uavlae.envs.config import EnvConfig
from uavlae.envs.physics import channel, min_return_energy, point_rect_distance

__all__ = ["run_problems", "world_problems"]


def world_problems(env: EnvConfig) -> list[str]:
    """The broken rules of the world ``env``, one line each (none: an empty list)."""
    out = []
    if env.ge.count.min < 1:
        # SPEC §5: DCR = Σ collected / Σ total, and a scenario without GEs lands at its first slot
        out.append(f"env.ge.count.min={env.ge.count.min}: a scenario without GEs has no data to collect (DCR = "
                   "collected / total is 0/0) and lands at once (every GE is empty); allowed: "
                   "1 <= env.ge.count.min <= env.ge.count.max")
    below = torch.tensor([[0.0, 0.0]])
    snr, _ = channel(below, below, env.area.altitude, env.ge.tx_power, env.channel)
    if float(snr) < env.channel.snr_threshold:
        # SPEC §3: the best SNR a GE can give is the one straight below the DCU, at d = H
        out.append(f"env.channel.snr_threshold={env.channel.snr_threshold:g} is above the SNR of a GE straight below "
                   f"the DCU ({float(snr):.3g} from env.ge.tx_power={env.ge.tx_power:g}, env.channel.alpha="
                   f"{env.channel.alpha:g}, env.channel.noise={env.channel.noise:g} at env.area.altitude="
                   f"{env.area.altitude:g}): no GE could ever be served; lower the threshold or the altitude")
    start = torch.tensor(env.area.start_xy)
    d_la = point_rect_distance(start, torch.tensor([env.area.landing]), torch.tensor([True]))
    if float(d_la) == 0.0:
        out.append(f"env.area.start={list(env.area.start_xy)} lies in the landing area env.area.landing="
                   f"{list(env.area.landing)}: the first slot at rest would land; move one of them")
    e_min = float(min_return_energy(d_la, env.energy, env.motion))
    if e_min > env.energy.e_limit:
        # SPEC §4 and §7 (r8): the straight flight from the start to LA at v_max is the cheapest way there
        out.append(f"env.energy.e_limit={env.energy.e_limit:g} J does not pay the straight flight from the start "
                   f"to the landing area at env.motion.v_max ({e_min:.0f} J): no episode could land; raise it to "
                   f"at least {e_min:.0f}")
    return out


# the learners that constrain ("next", "cost")
COST_LEARNERS = frozenset({"sac_lag", "cpo"})
# the learners whose update reads the acting policy's log-probability of the stored action
ON_POLICY_LEARNERS = frozenset({"ppo", "cpo", "wang", "theile"})
# the learners whose actor is deterministic (no policy to draw from)
DETERMINISTIC_LEARNERS = frozenset({"ddpg"})


def run_problems(cfg: Any, env: EnvConfig) -> list[str]:
    """The broken rules of a composed run config ``cfg`` (validated already) flying the world ``env``."""
    out = world_problems(env)
    advisor = cfg.get("advisor")
    if advisor is not None and advisor.kind != "none" and advisor.mode == "fixed_prob" and float(advisor.fp) == 0:
        out.append(f"advisor.mode=fixed_prob with advisor.fp=0: the {advisor.kind} advisor would never be asked, "
                   "so the run is plain SAC under another name; allowed: 0 < advisor.fp <= 1")
    sf = cfg.get("safety_filter")
    if sf is not None:
        trained = {k: v for k, v in (("penalty", float(sf.penalty)), ("cost", float(sf.cost))) if v > 0}
        if sf.learn_from != "executed":
            trained["learn_from"] = sf.learn_from
        if trained and sf.mode != "train_and_deploy":
            keys = " ".join(f"safety_filter.{k}={v}" for k, v in trained.items())
            out.append(f"{keys} with safety_filter.mode={sf.mode}: nothing is filtered in training, so they would "
                       "change nothing; use safety_filter.mode=train_and_deploy or drop them")
        algo = cfg.get("algo")
        if (sf.mode == "train_and_deploy" and sf.learn_from == "executed" and algo is not None
                and algo.name in ON_POLICY_LEARNERS):
            out.append(f"safety_filter.mode=train_and_deploy with algo={algo.name} and safety_filter.learn_from=executed: "
                       "an on-policy learner's stored log-probability is the wish's, so the executed action would "
                       "give it a wrong ratio; use safety_filter.learn_from=proposed")
        if float(sf.cost) > 0 and algo is not None and algo.name not in COST_LEARNERS:
            out.append(f"safety_filter.cost={float(sf.cost):g} with algo={algo.name}: that learner reads no cost, so "
                       f"the filter's cost would change nothing; allowed with algo in {sorted(COST_LEARNERS)}")
    tr, algo = cfg.get("trainer"), cfg.get("algo")
    if (tr is not None and tr.get("eval_actor", "mean") == "sample" and algo is not None
            and algo.name in DETERMINISTIC_LEARNERS):
        out.append(f"trainer.eval_actor=sample with algo={algo.name}: its actor is deterministic, there is no policy "
                   "to draw from; use trainer.eval_actor=mean")
    return out
