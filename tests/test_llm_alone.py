"""The LLM alone (uavlae.llm_alone, +exp=llm): what it sees (the 20 m view), its call budget,
resuming without flying a finished episode again, and what it cost."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from uavlae.llm import WorldLimits, advisor_states_from_tensordict, build_messages, make_llm_config

LIM = WorldLimits(x_size=500.0, y_size=500.0, v_max=10.0, v_limit=5.0, perception_radius=20.0,
                  landing=(475.0, 0.0, 500.0, 25.0), e_limit=8e5)


def _hand_state() -> TensorDict:
    """One DCU at (100, 100) with, worked out by hand:
    BZ (110, 90, 130, 110): its west edge 10 m east of the DCU -> in view;
    NFZ (60, 115, 90, 200): its corner (90, 115) at hypot(10, 15) = 18.0 m, its centre ~110 m -> in view;
    NFZ (300, 300, 350, 350): ~283 m -> out;
    RZ (125, 80, 140, 120): its west edge exactly 25 m east -> out;
    OU at (110, 100): 10 m -> in view; OU at (100, 122): 22 m -> out;
    GEs at (400, 400), (20, 480), (101, 99), all with data -> all three shown, wherever they are."""
    one = TensorDict({
        "position": torch.tensor([[100.0, 100.0]]), "velocity": torch.tensor([[1.0, -2.0]]),
        "energy_used": torch.tensor([5e4]), "energy_left": torch.tensor([7.5e5]),
        "ge_pos": torch.tensor([[[400.0, 400.0], [20.0, 480.0], [101.0, 99.0]]]),
        "ge_remaining": torch.tensor([[3.0, 0.5, 1.25]]), "ge_mask": torch.ones(1, 3, dtype=torch.bool),
        "ou_pos": torch.tensor([[[110.0, 100.0], [100.0, 122.0]]]), "ou_vel": torch.tensor([[[-1.0, 0.0], [0.0, -3.0]]]),
        "ou_mask": torch.ones(1, 2, dtype=torch.bool),
        "bz": torch.tensor([[[110.0, 90.0, 130.0, 110.0]]]), "bz_mask": torch.ones(1, 1, dtype=torch.bool),
        "nfz": torch.tensor([[[60.0, 115.0, 90.0, 200.0], [300.0, 300.0, 350.0, 350.0]]]),
        "nfz_mask": torch.ones(1, 2, dtype=torch.bool),
        "rz": torch.tensor([[[125.0, 80.0, 140.0, 120.0]]]), "rz_mask": torch.ones(1, 1, dtype=torch.bool),
        "d_bz": torch.tensor([10.0]), "d_nfz": torch.tensor([18.03]), "d_rz": torch.tensor([25.0]),
        "d_ou": torch.tensor([10.0]), "d_boundary": torch.tensor([100.0]), "d_la": torch.tensor([380.0]),
    }, batch_size=[1])
    return TensorDict({"state": one}, batch_size=[1])


def test_local_view_shows_what_lies_within_20_m_every_ge_and_e_limit():
    (s,) = advisor_states_from_tensordict(_hand_state(), [0], LIM, view_radius=20.0)
    assert s.bz == ((110.0, 90.0, 130.0, 110.0),)
    assert s.nfz == ((60.0, 115.0, 90.0, 200.0),)  # the far NFZ is gone
    assert s.rz == ()  # 25 m away
    assert [(o.x, o.y) for o in s.ous] == [(110.0, 100.0)]
    assert [(g.x, g.y, g.remaining) for g in s.ges] == [(400.0, 400.0, 3.0), (20.0, 480.0, 0.5), (101.0, 99.0, 1.25)]
    assert (s.d_bz, s.d_ou, s.d_rz, s.d_la) == (10.0, 10.0, math.inf, 380.0)  # the RZ's 25 m is out of view
    assert "(300.0, 300.0, 350.0, 350.0)" in s.episode and "(125.0, 80.0, 140.0, 120.0)" in s.episode  # slot key: whole map

    system, user = (m["content"] for m in build_messages(s, view="local", view_radius=20.0))
    assert "Buildings (BZ): (110,90,130,110)\n" in user
    assert "NFZs: (60,115,90,200)\n" in user and "300,300" not in user
    assert "RZs: none\n" in user and "125,80" not in user
    assert "OUs within 20 m (x, y, vx, vy): (110,100,-1.0,0)\n" in user and "122" not in user
    assert "GEs with remaining data (x, y, data): (400,400,3.0) (20,480,0.5) (101,99,1.2)\n" in user
    assert user.endswith("DCU position (100, 100) m, velocity (1.0, -2.0) m/s, energy left 750000 J of "
                         "E_limit 800000 J.")
    assert "energy budget E_limit = 800000 J" in system

    # the full view (SAC+LLM's default) is unchanged: every zone, no energy
    (full,) = advisor_states_from_tensordict(_hand_state(), [0], LIM)
    assert full.rz == ((125.0, 80.0, 140.0, 120.0),) and len(full.nfz) == 2 and full.episode == ""
    _, user_full = (m["content"] for m in build_messages(full))
    assert "RZs: (125,80,140,120)" in user_full and "energy" not in user_full

    with pytest.raises(ValueError, match="prompt view must be one of"):
        build_messages(s, view="near")
    with pytest.raises(ValueError, match="llm.view"):
        make_llm_config("local", view="near")
    with pytest.raises(ValueError, match="llm.view_radius"):
        make_llm_config("local", view_radius=0.0)


def test_the_advisor_adapter_sends_the_local_view():
    from uavlae.envs import make_env_config
    from uavlae.llm import LLMAdvisor
    from uavlae.policies.override import LLMAdvisorAdapter

    adv = LLMAdvisor(make_llm_config("local", view="local", cache_mode="off"), base_url="http://127.0.0.1:9/v1")
    adapter = LLMAdvisorAdapter(adv, make_env_config(None))
    (s,) = advisor_states_from_tensordict(_hand_state(), [0], adapter.limits, view_radius=adv.cfg.view_radius)
    assert adv.request_body(s)["messages"][1]["content"].startswith("Landing area")
    assert "Zones with any part within 20 m" in adv.request_body(s)["messages"][1]["content"]
    adv.close()


# ---------------------------------------------------------------------------- budget and resume


def _world(n: int):
    from uavlae.envs import make_env_config
    from uavlae.envs.scenario import sample_scenarios, unstack_scenarios

    cfg = make_env_config({"t_max": 80})  # short enough that one of these episodes lands before the others end
    return cfg, unstack_scenarios(sample_scenarios(cfg, n, torch.Generator().manual_seed(7)))


def _heuristic_always(cfg):
    """The greedy heuristic as the advisor of an always-triggered override: a real advisor that
    answers at once, so the budget and the resume are checked on hundreds of decisions."""
    from uavlae.policies.greedy import GreedyPolicy
    from uavlae.policies.override import HeuristicAdvisor, OverridePolicy

    h = GreedyPolicy(cfg)
    return OverridePolicy(h, HeuristicAdvisor(h), mode="always", fallback="policy")


def _evaluation(cfg, scen, out, **kw):
    from uavlae.llm_alone import LLMAloneEvaluation

    return LLMAloneEvaluation(cfg, scen, _heuristic_always(cfg), out, seed=3, n_plots=0,
                              fingerprint={"what": "test"}, **kw)


def test_one_chunk_flies_what_the_evaluator_flies(tmp_path):
    from uavlae.evaluate import Evaluator

    cfg, scen = _world(3)
    res = _evaluation(cfg, scen, tmp_path / "a").run()
    ref = Evaluator(cfg, scen, seed=3, n_plots=0).run(_heuristic_always(cfg))
    assert res["complete"] and res["episodes_scored"] == 3 and res["chunks"] == 1
    for k in ("DCR", "CR", "SLR", "RVR", "ECR", "mean_return", "mean_length"):
        assert res["metrics"][k] == pytest.approx(ref[k], nan_ok=True), k
    # one decision per row and step while its episode runs, none after it ended (row 1 lands first)
    lengths = res["records"]["length"].tolist()
    assert lengths == [80, 77, 80] and res["records"]["landed"].tolist() == [False, True, False]
    assert res["records"]["llm_calls"].tolist() == lengths
    assert res["cost"]["calls"] == int(res["records"]["length"].sum()) == res["cost"]["calls_scored"]
    # the pictures' GEs at the data they held when each episode ended: what left them is what it
    # collected, and the evaluator's rollout keeps the same
    from uavlae.envs.metrics import rollout_metrics
    from uavlae.evaluate import EpisodeEnds

    left = res["ge_left"][0]
    for i, sc in enumerate(scen):
        got = sum(sc.ge_data) - float(left[i].sum())
        assert got == pytest.approx(float(res["records"]["data_collected"][i]), abs=1e-4)
    ev, ends = Evaluator(cfg, scen, seed=3, n_plots=0), EpisodeEnds()
    ev.env.set_seed(3)
    rollout_metrics(ev.env, _heuristic_always(cfg), cfg=cfg, on_step=ends)
    assert torch.equal(ends.ge_left, left)
    # a bare controller (no override, its memory kept through cache_state) flies the same
    from uavlae.llm_alone import LLMAloneEvaluation
    from uavlae.policies.greedy import GreedyPolicy

    bare = LLMAloneEvaluation(cfg, scen, GreedyPolicy(cfg), tmp_path / "b", seed=3, chunk=2, n_plots=0).run()
    assert bare["records"]["length"].tolist() == lengths and bare["cost"]["fallbacks"] == 0


def test_budget_pauses_and_the_same_run_continues_without_flying_an_episode_again(tmp_path):
    from uavlae.llm_alone import LLMAloneEvaluation

    cfg, scen = _world(3)
    straight = _evaluation(cfg, scen, tmp_path / "straight", chunk=1).run()
    lengths = straight["records"]["length"].tolist()
    total = sum(lengths)
    assert straight["complete"] and straight["cost"]["calls"] == total and total > 30

    budget = lengths[0] + 5  # chunk 0 and 5 steps of chunk 1 fit in the first invocation
    out = tmp_path / "paused"
    first_ev = _evaluation(cfg, scen, out, chunk=1, budget=budget)
    first = first_ev.run()
    assert not first["complete"] and first["chunks_done"] == 1 and first["episodes_scored"] == 1
    assert first_ev.asked == budget and first["in_flight_step"] == 5
    assert first["cost"]["calls"] == budget and first["cost"]["calls_scored"] == lengths[0]
    assert first["metrics"]["DCR"] == pytest.approx(
        float(straight["records"]["data_collected"][0] / straight["records"]["data_total"][0]))

    asked = [first_ev.asked]
    res = first
    while not res["complete"]:  # the same command again, a fresh process's objects each time
        ev = _evaluation(cfg, scen, out, chunk=1, budget=budget)
        res = ev.run()
        asked.append(ev.asked)
        assert len(asked) < 10
    assert sum(asked) == total  # nothing flown twice
    assert res["invocations"] == len(asked)
    for k in ("length", "data_collected", "energy_used", "collided", "landed", "llm_calls"):
        assert res["records"][k].tolist() == straight["records"][k].tolist(), k
    assert res["cost"]["calls"] == total == int(res["records"]["llm_calls"].sum())
    assert res["cost"]["calls_in_flight"] == 0
    # the policy's own counters travelled through every pause
    assert res["cost"]["fallbacks"] == 0 and ev.policy.run_totals()["advised"] == total

    # a finished run flies nothing more; another config's progress is refused
    again = _evaluation(cfg, scen, out, chunk=1, budget=budget)
    assert again.run()["complete"] and again.asked == 0
    with pytest.raises(ValueError, match="another config"):
        _evaluation(cfg, scen, out, chunk=2).run()
    with pytest.raises(ValueError, match=r"another config \(differs in \['what'\]\)"):
        LLMAloneEvaluation(cfg, scen, _heuristic_always(cfg), out, seed=3, chunk=1, fingerprint={"what": "other"}).run()
    # a setting the file's config lacks (added to the code since) is not a difference
    newer = LLMAloneEvaluation(cfg, scen, _heuristic_always(cfg), out, seed=3, chunk=1, n_plots=0,
                               fingerprint={"what": "test", "added": None})
    assert newer.run()["complete"] and newer.asked == 0
    with pytest.raises(ValueError, match="llm_call_budget=1 is below the 3 rows"):
        _evaluation(cfg, scen, tmp_path / "x", budget=1)


def test_ctrl_c_pauses_at_the_last_saved_slot(tmp_path):
    cfg, scen = _world(2)
    straight = _evaluation(cfg, scen, tmp_path / "straight", chunk=1).run()

    ev = _evaluation(cfg, scen, tmp_path / "c", chunk=1)
    act, calls = ev.policy.forward, []

    def interrupted(td):  # fault injection: Ctrl-C during the 100th decision
        calls.append(1)
        if len(calls) == 100:
            raise KeyboardInterrupt
        return act(td)

    ev.policy.forward = interrupted
    res = ev.run()
    first = straight["records"]["length"].tolist()[0]
    assert not res["complete"] and res["chunks_done"] == 1 and res["in_flight_step"] == 99 - first
    assert res["cost"]["calls"] == 99 and ev.policy.run_totals()["advised"] == 99
    done = _evaluation(cfg, scen, tmp_path / "c", chunk=1).run()
    assert done["complete"] and done["records"]["length"].tolist() == straight["records"]["length"].tolist()
    assert done["cost"]["calls"] == straight["cost"]["calls"]


def test_two_shards_fly_each_its_chunks_into_one_folder_and_score_the_union(tmp_path):
    cfg, scen = _world(3)
    straight = _evaluation(cfg, scen, tmp_path / "straight", chunk=1).run()
    lengths = straight["records"]["length"].tolist()
    out = tmp_path / "sharded"

    # shard 1 of 2 owns chunk 1 only; paused by its budget a few steps in
    s1 = _evaluation(cfg, scen, out, chunk=1, shard=1, shards=2, budget=10).run()
    assert s1["chunks_done"] == 0 and s1["in_flight_step"] == 10 and s1["progress_files"] == 1
    # shard 0 owns chunks 0 and 2 and flies both; it scores what it finished, shard 1's in-flight
    # decisions counted but not scored
    s0 = _evaluation(cfg, scen, out, chunk=1, shard=0, shards=2).run()
    assert s0["chunks_done"] == 2 and not s0["complete"] and s0["records"]["row"].tolist() == [0, 2]
    assert s0["cost"]["calls"] == lengths[0] + lengths[2] + 10 and s0["cost"]["calls_in_flight"] == 10
    assert sorted(p.name for p in out.iterdir() if p.suffix == ".pt") == ["progress.shard0of2.pt", "progress.shard1of2.pt"]
    # shard 1 again: finishes chunk 1, then sees every chunk done
    ev1 = _evaluation(cfg, scen, out, chunk=1, shard=1, shards=2)
    done = ev1.run()
    assert ev1.asked == lengths[1] - 10 and done["complete"] and done["progress_files"] == 2
    for k in ("row", "length", "data_collected", "energy_used", "collided", "landed", "llm_calls"):
        assert done["records"][k].tolist() == straight["records"][k].tolist(), k
    for k in ("DCR", "CR", "SLR", "RVR", "ECR", "mean_return"):
        assert done["metrics"][k] == pytest.approx(straight["metrics"][k], nan_ok=True), k
    assert done["cost"]["calls"] == sum(lengths) and done["cost"]["calls_in_flight"] == 0
    assert done["cost"]["invocations"] == 3  # shard 0 once, shard 1 twice
    assert [i for i, _ in done["trajectories"]] == [0, 1, 2]

    # one process over the same folder flies nothing: every chunk is done in the shards' files;
    # a budget of 0 asks nothing and scores the same union
    for kw in ({}, {"budget": 0}):
        ev = _evaluation(cfg, scen, out, chunk=1, **kw)
        res = ev.run()
        assert ev.asked == 0 and res["complete"] and res["records"]["length"].tolist() == lengths
    with pytest.raises(ValueError, match="eval_shard=2 must be in"):
        _evaluation(cfg, scen, out, chunk=1, shard=2, shards=2)


def test_a_progress_file_of_the_first_format_continues(tmp_path):
    """Format 1 kept chunks in order (``next_chunk``) and every episode's path in one list."""
    cfg, scen = _world(3)
    straight = _evaluation(cfg, scen, tmp_path / "straight", chunk=1).run()
    lengths = straight["records"]["length"].tolist()
    out = tmp_path / "old"
    _evaluation(cfg, scen, out, chunk=1, budget=lengths[0] + lengths[1] + 7).run()  # chunks 0, 1 done, 2 in flight
    state = torch.load(out / "progress.pt", weights_only=False)
    assert state["done"] == [0, 1] and state["in_flight"]["chunk"] == 2
    del state["in_flight"]["chunk"]
    old = {k: v for k, v in state.items() if k not in ("done", "totals")}
    old.update(version=1, next_chunk=2, trajectories=[t for ts in state["trajectories"] for t in ts])
    torch.save(old, out / "progress.pt")

    ev = _evaluation(cfg, scen, out, chunk=1)
    res = ev.run()
    assert ev.asked == lengths[2] - 7 and res["complete"]
    assert res["records"]["length"].tolist() == lengths and [i for i, _ in res["trajectories"]] == [0, 1, 2]
    assert [len(t) for _, t in res["trajectories"]] == [n + 1 for n in lengths]
    assert torch.load(out / "progress.pt", weights_only=False)["version"] == 2


# ---------------------------------------------------------------------------- the real local server


def _cfg(*overrides: str):
    from hydra import compose, initialize_config_dir

    from uavlae.factories import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _llm_run_args(tmp_path, server, episodes: int, max_steps: int, plots: int) -> list[str]:
    """``+exp=llm`` on the local ``server``: a run of ``episodes`` one-scenario chunks cut at
    ``max_steps``, reused by re-runs, with no wandb or progress bar."""
    return ["+exp=llm", f"run_dir={tmp_path / 'llm'}", f"llm.base_url={server.base_url}",
            f"llm.cache_path={tmp_path / 'cache.sqlite'}", f"trainer.eval_episodes={episodes}",
            "trainer.eval_chunk=1", f"trainer.eval_max_steps={max_steps}", f"trainer.eval_plots={plots}",
            "trainer.progress_bar=false", "logger.wandb.mode=disabled", "experiment.reuse=true"]


@pytest.mark.integration
@pytest.mark.timeout(600)
def test_exp_llm_on_the_local_server_pauses_on_its_budget_and_continues(tmp_path, local_llm):
    from uavlae.train import reuse_state, run

    run_dir = tmp_path / "llm"
    args = _llm_run_args(tmp_path, local_llm, episodes=2, max_steps=3, plots=1)
    first = run(_cfg(*args, "trainer.llm_call_budget=4"))
    # scenario 0's 3 steps, then 1 step of scenario 1 fits; the next would be the 5th decision
    assert first["eval/complete"] == 0 and first["eval/episodes_scored"] == 1 and first["eval/episodes_total"] == 2
    assert first["llm/calls"] == 4 and first["llm/calls_scored"] == 3 and first["llm/calls_in_flight"] == 1
    assert "eval/DCR" in first and math.isfinite(first["eval/DCR"])
    assert reuse_state(_cfg(*args, "trainer.llm_call_budget=4"))[0] == "new"  # paused: a sweep re-run continues

    final = run(_cfg(*args, "trainer.llm_call_budget=4"))
    assert final["eval/complete"] == 1 and final["eval/episodes_scored"] == 2
    rows = list(csv.DictReader((run_dir / "eval" / "frames_000000000" / "episodes.csv").open()))
    per_episode = [int(r["llm_calls"]) for r in rows]
    assert per_episode == [int(r["length"]) for r in rows] == [3, 3]
    # the cost: calls = the sum over episodes; each a request to the advisor; tokens counted
    assert final["llm/calls"] == sum(per_episode) == final["override/advised"] == final["llm/requests"] == 6
    assert final["llm/http_calls"] + final["llm/cache_hits"] >= 6
    assert final["llm/prompt_tokens"] > 0 and final["llm/completion_tokens"] > 0
    assert final["llm/wall_s"] > 0 and final["llm/calls_per_s"] == pytest.approx(6 / final["llm/wall_s"])
    assert final["llm/invocations"] == 2 and final["llm/fallbacks"] == final["override/source/fallback"]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["llm_alone"]["complete"] == 1 and summary["llm_alone"]["cost"]["calls"] == 6
    assert reuse_state(_cfg(*args, "trainer.llm_call_budget=4"))[0] == "done"
    assert (Path(run_dir) / "eval" / "frames_000000000" / "trajectory_0.png").is_file()


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_evaluate_entry_point_flies_the_llm_alone_the_same_way(tmp_path, local_llm):
    from uavlae.evaluate import evaluate_checkpoint

    out = tmp_path / "ev"
    args = ["+exp=llm", f"experiment.eval_dir={out}", f"llm.base_url={local_llm.base_url}",
            f"llm.cache_path={tmp_path / 'cache.sqlite'}", "trainer.eval_episodes=2", "trainer.eval_max_steps=2",
            "trainer.eval_plots=0", "experiment.reuse=true"]
    evaluate_checkpoint(_cfg(*args, "trainer.llm_call_budget=2"))  # both rows' first slot, then paused
    rec = json.loads((out / "evaluation.json").read_text())
    assert rec["llm_alone"]["complete"] is False and rec["llm_alone"]["cost"]["calls"] == 2
    agg = evaluate_checkpoint(_cfg(*args, "trainer.llm_call_budget=2"))  # reuse continues a paused one
    rec = json.loads((out / "evaluation.json").read_text())
    assert rec["llm_alone"]["complete"] is True and rec["llm_alone"]["episodes_scored"] == 2 == agg["n_episodes"]
    assert rec["llm_alone"]["cost"]["calls"] == 4 == rec["controller_stats"]["advised"]


@pytest.mark.integration
@pytest.mark.timeout(600)
def test_exp_llm_in_two_shards_on_the_local_server_fills_one_run(tmp_path, local_llm):
    from uavlae.experiments.llm_alone_table import build, markdown
    from uavlae.train import reuse_state, run

    run_dir = tmp_path / "llm"
    args = [*_llm_run_args(tmp_path, local_llm, episodes=3, max_steps=2, plots=0), "trainer.eval_shards=2"]
    one = run(_cfg(*args, "trainer.eval_shard=1"))  # scenario 1 (chunk 1 of 3) only
    assert one["eval/complete"] == 0 and one["eval/episodes_scored"] == 1 and one["llm/calls"] == 2
    # the same run_dir, the other shard: not "another config"; it flies chunks 0 and 2 and scores all three
    assert reuse_state(_cfg(*args, "trainer.eval_shard=0"))[0] == "new"
    both = run(_cfg(*args, "trainer.eval_shard=0"))
    assert both["eval/complete"] == 1 and both["eval/episodes_scored"] == 3
    assert both["llm/calls"] == 6 == both["llm/calls_scored"] and both["llm/invocations"] == 2
    assert both["llm/requests"] >= 6 and both["llm/prompt_tokens"] > 0  # shard 1's tokens counted too
    rows = list(csv.DictReader((run_dir / "eval" / "frames_000000000" / "episodes.csv").open()))
    assert [int(r["row"]) for r in rows] == [0, 1, 2] and [int(r["llm_calls"]) for r in rows] == [2, 2, 2]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert (summary["llm_alone"]["shard"], summary["llm_alone"]["shards"]) == (0, 2)
    assert reuse_state(_cfg(*args, "trainer.eval_shard=1"))[0] == "done"
    table = build(run_dir, "test")
    assert table["episodes_scored"] == 3 and [e["scenario"] for e in table["episodes"]] == [0, 1, 2]
    assert table["in_flight_so_far"] == [] and table["heuristic_same_scenarios"]["mean_length"] == 2.0
    assert "| llm | 3 |" in markdown(table)
