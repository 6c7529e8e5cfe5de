"""What an advisor's answer is worth, scored by the environment's own physics.

A fixed, saved set of triggered states (``benchmarks/advice_states.pt``, built once with
``--collect`` from real rollouts: half the rows flown by the heuristic, half by a uniform random
policy, every state where the override's proximity trigger fires, then picked evenly by the
kind of the nearest obstacle: building, NFZ, RZ, other UAV). Every advisor answers each state
once; the answer is executed from that exact state, and then held for ``--hold`` slots, by the
env's step, with the env's generator seeded identically before every advisor's run, so all of
them meet the same OU motion. Scores per advisor (fractions of its states):

- ``bz``/``nfz``/``ou`` collision, ``rz_speeding``, ``boundary_exit``, ``any_violation`` on the
  next slot (``_1``) and within the ``--hold`` slots (``_H``, counted until a row is done);
- ``progress_1_m``/``progress_H_m``: metres gained toward the current target (the nearest GE
  with data left, else the landing area, fixed at the state the advice answers);
- ``valid``: answers that passed the extractor (a failed one is scored as a hover);
- ``latency_p50_s``/``latency_p95_s`` per answer, and the LLM's tokens per call.

- ``paper_example``: answers that are the velocity of the paper's example answer (4.2, 1.6) m/s
  (a model that copies part (c)'s example), ``top_answer``: the share of the most common answer;
  ``calls``: HTTP calls per state (more than one: an answer was rejected and asked again).

Advisors: ``llm`` (the local LLM with uavlae/conf/llm/local.yaml), ``llm_verbose`` (the earlier
default: the longer observation, ``json_schema``, a 200-character Reasoning), and variants one
setting away from the compact prompt with the paper's example (``llm_paper_example``): what
makes the gap to ``llm_verbose`` (``llm_verbose_obs``, ``llm_verbose_grammar``,
``llm_json_schema``), what the example answer does (``llm_placeholder``: a format-only
example, ``llm_no_example``, ``llm_reasoning_first``: the Reasoning before the action), the
paper's ablations (``llm_no_safety``/``llm_no_compliance``/``llm_no_data``/``llm_no_energy``);
``LLM_VARIANTS`` holds each one's settings. Then ``heuristic``, ``hover``, ``random`` (uniform
in the speed disc), ``actor`` (an exported actor, ``--actor FILE.pt2``), ``endpoint`` (any
OpenAI-compatible server, ``--endpoint PRESET_OR_YAML``) and ``student`` (the student advisor of a
run with ``advisor.amortize``, taken from its checkpoint, ``--student RUN_DIR``: its own answer
on every state, never the LLM's; compared state by state with ``llm`` below, with the mean gap
between the two answers in m/s). LLM advisors run with the advice
cache off. Every state is stepped in one batch with the whole set (the states beyond ``--n``
hover), so a state meets the same draws in every run. Results of separate runs, also of two
at once, merge into ``benchmarks/advice_quality.json`` (per advisor) and the table
``benchmarks/advice_quality.md``; an advisor run on the first N states only (``--n``) is also
compared there with every other advisor on those same N states, each LLM prompt state by state
against ``llm`` and ``llm_verbose`` (paired 95% bootstrap intervals). ``--rescore`` scores the
stored answers again (no advisor is asked).

    python benchmarks/advice_quality.py --collect
    python benchmarks/advice_quality.py --advisors heuristic hover random llm
    python benchmarks/advice_quality.py --advisors llm_verbose llm_no_safety --n 50
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable

import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uavlae.envs import UAVEnv, make_env_config  # noqa: E402
from uavlae.envs.world import current_target  # noqa: E402
from uavlae.files import atomic_write, dump_json, portable  # noqa: E402
from uavlae.llm import Advice, LLMAdvisor, WorldLimits, advisor_states_from_tensordict, make_llm_config  # noqa: E402
from uavlae.llm.prompt import PAPER_EXAMPLE_VELOCITY  # noqa: E402
from uavlae.machine import describe_machine  # noqa: E402
from uavlae.policies.heuristic import HeuristicPolicy  # noqa: E402

STATES = ROOT / "benchmarks" / "advice_states.pt"
OUT = ROOT / "benchmarks" / "advice_quality.json"
TABLE = ROOT / "benchmarks" / "advice_quality.md"
KINDS = ("bz", "nfz", "rz", "ou")
EVENTS = ("bz_collision", "nfz_entry", "ou_collision", "rz_speeding", "boundary_exit")
# LLM config overrides of each advisor; every one is one setting away from the compact prompt
# with the paper's example answer (llm_paper_example), so that each names what it changes
PAPER = {"example": "paper"}
LLM_VARIANTS = {"llm": {},  # the default (uavlae/conf/llm/local.yaml)
                "llm_verbose": {**PAPER, "observation": "verbose", "reasoning_max_chars": 200,
                                "response_format": "json_schema", "max_tokens": 160},  # the earlier default
                "llm_paper_example": PAPER,
                # which difference to llm_verbose matters
                "llm_verbose_obs": {**PAPER, "observation": "verbose"},  # with its part (c) style and grammar
                "llm_verbose_grammar": {**PAPER, "grammar_style": "verbose"},  # spaces, two decimals
                "llm_json_schema": {**PAPER, "response_format": "json_schema"},
                # and whether the model answers the state or copies part (c)'s example
                # (llm itself: example placeholder)
                "llm_no_example": {"example": "none"},
                "llm_reasoning_first": {**PAPER, "reasoning_first": True},
                **{f"llm_{a}": {**PAPER, "prompt_ablation": a} for a in ("no_safety", "no_compliance", "no_data", "no_energy")}}
ADVISORS = (*LLM_VARIANTS, "heuristic", "hover", "random", "actor", "endpoint", "student")


def _atomic_save(obj: Any, path: Path) -> None:
    atomic_write(path, lambda fh: torch.save(obj, fh))


def _distances(state: TensorDict, pr: float) -> torch.Tensor:
    """[n, 4] distances to the nearest BZ, NFZ, RZ and visible OU (as the trigger reads them)."""
    d_ou = state["d_ou"].masked_fill(state["d_ou"] > pr, math.inf)
    return torch.stack([state["d_bz"], state["d_nfz"], state["d_rz"], d_ou], -1)


# ------------------------------------------------------------------ the saved states
def collect(args: argparse.Namespace) -> None:
    """Roll out B rows (half heuristic, half uniform random) and keep the triggered states."""
    env_cfg = make_env_config(None)
    B, pr = args.rollout_batch, env_cfg.safety.perception_radius
    env = UAVEnv(env_cfg, batch_size=B, seed=args.seed)
    heuristic = HeuristicPolicy(env_cfg)
    g = torch.Generator().manual_seed(args.seed)
    td = env.reset()
    found: list[TensorDict] = []
    kind_of: list[int] = []
    driver_of: list[int] = []
    for _ in range(args.rollout_steps):
        st = td["state"]
        d = _distances(st, pr)
        near, which = d.min(-1)
        trig = near <= args.d_th
        if trig.any():
            rows = trig.nonzero().squeeze(-1)
            found.append(st[rows].clone())
            kind_of += which[rows].tolist()
            driver_of += (rows >= B // 2).long().tolist()  # 0 heuristic, 1 random
        action = heuristic.act(st)
        action[B // 2:] = torch.rand(B - B // 2, 2, generator=g) * 2 - 1
        td["action"] = action
        _, td = env.step_and_maybe_reset(td)
    pool = torch.cat(found, 0)
    kinds = torch.tensor(kind_of)
    perm = torch.randperm(pool.batch_size[0], generator=g)
    per_kind = {k: [int(i) for i in perm if kinds[i] == k] for k in range(len(KINDS))}
    picked: list[int] = []
    while len(picked) < args.n_states and any(per_kind.values()):
        for k in range(len(KINDS)):  # round robin over the kinds: any first N are balanced too
            if per_kind[k] and len(picked) < args.n_states:
                picked.append(per_kind[k].pop(0))
    idx = torch.tensor(picked)
    chosen = pool[idx]
    keep = [k for k in chosen.keys() if k != "geo_field"]
    data = {"state": chosen.select(*keep).to_dict(), "kind": [KINDS[int(kinds[i])] for i in idx],
            "driver": [("heuristic", "random")[driver_of[int(i)]] for i in idx],
            "d_th": args.d_th, "seed": args.seed, "rollout_batch": B, "rollout_steps": args.rollout_steps,
            "triggered_seen": int(pool.batch_size[0])}
    _atomic_save(data, STATES)
    counts = {k: data["kind"].count(k) for k in KINDS}
    print(f"saved {len(picked)} of {pool.batch_size[0]} triggered states to {STATES}: {counts}")


def load_states(path: Path) -> tuple[TensorDict, dict[str, Any], str]:
    data = torch.load(path, weights_only=True)
    n = len(data["kind"])
    state = TensorDict(data["state"], batch_size=[n])
    digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    return state, data, digest


# ------------------------------------------------------------------ scoring
def score(env: UAVEnv, state: TensorDict, action: torch.Tensor, hold: int, seed: int) -> dict[str, torch.Tensor]:
    """Execute ``action`` from ``state`` and hold it ``hold`` slots; per-row events and progress."""
    n = state.batch_size[0]
    vec, _, _ = current_target(dict(state.items()))
    target = state["position"] + vec
    d0 = torch.linalg.vector_norm(vec, dim=-1)
    env.set_seed(seed)  # the same OU motion and draws for every advisor
    alive = torch.ones(n, dtype=torch.bool)
    hit = {k: torch.zeros(n, dtype=torch.bool) for k in EVENTS}
    first: dict[str, torch.Tensor] = {}
    pos = state["position"].clone()
    progress_1 = torch.zeros(n)
    cur = state.clone()
    for t in range(hold):
        out = env.step(TensorDict({"state": cur, "action": action}, batch_size=[n]))["next"]
        for k in EVENTS:
            hit[k] |= out["events", k].reshape(n) & alive
        new_pos = out["state", "position"]
        pos = torch.where(alive[:, None], new_pos, pos)
        if t == 0:
            first = {k: v.clone() for k, v in hit.items()}
            progress_1 = d0 - torch.linalg.vector_norm(target - pos, dim=-1)
        alive &= ~out["done"].reshape(n)
        cur = out["state"]
    res = {f"{k}_1": first[k].float() for k in EVENTS}
    res.update({f"{k}_H": hit[k].float() for k in EVENTS})
    res["any_violation_1"] = torch.stack([first[k] for k in EVENTS]).any(0).float()
    res["any_violation_H"] = torch.stack([hit[k] for k in EVENTS]).any(0).float()
    res["progress_1_m"] = progress_1
    res["progress_H_m"] = d0 - torch.linalg.vector_norm(target - pos, dim=-1)
    return res


def score_first(env: UAVEnv, full: TensorDict, action: torch.Tensor, hold: int, seed: int) -> dict[str, torch.Tensor]:
    """:func:`score` of answers to the first ``len(action)`` states, stepped in one batch with
    the whole set (the rest hover), so that a state meets the same draws whatever ``--n`` is."""
    n = action.shape[0]
    padded = torch.zeros(full.batch_size[0], 2)
    padded[:n] = action
    return {k: v[:n] for k, v in score(env, full, padded, hold, seed).items()}


# ------------------------------------------------------------------ advisors
def llm_answers(state: TensorDict, env_cfg: Any, cfg: Any, log_every: int = 25) -> dict[str, Any]:
    limits = WorldLimits.from_env_config(env_cfg)
    states = advisor_states_from_tensordict(TensorDict({"state": state}, batch_size=state.batch_size),
                                            list(range(state.batch_size[0])), limits)
    action = torch.zeros(len(states), 2)
    valid, latency, ptok, cached, ctok, calls, rejected = [], [], [], [], [], [], Counter()
    with LLMAdvisor(cfg) as adv:
        adv.advise_sync(states[:1])  # starts the server outside the timing; not scored
        for i, s in enumerate(states):
            adv.stats.reset()
            t0 = time.perf_counter()
            (r,) = adv.advise_sync([s])
            latency.append(time.perf_counter() - t0)
            snap = adv.stats.snapshot()
            ptok.append(snap["prompt_tokens"])
            cached.append(snap["cached_prompt_tokens"])
            calls.append(snap["calls"])  # more than one: answers rejected and asked again
            rejected.update({k.split("/", 1)[1]: int(v) for k, v in snap.items() if k.startswith("rejected/")})
            ctok.append(snap["completion_tokens"])
            valid.append(isinstance(r, Advice))
            if isinstance(r, Advice):
                action[i] = torch.tensor(r.action(limits.v_max))
            if log_every and (i + 1) % log_every == 0:
                print(f"  {i + 1}/{len(states)} answered, last {latency[-1]:.2f} s", flush=True)
    return {"action": action.clamp(-1, 1), "valid": valid, "latency": latency, "prompt_tokens": ptok,
            "cached_prompt_tokens": cached, "completion_tokens": ctok, "calls": calls, "rejected": dict(rejected)}


def student_answers(state: TensorDict, env_cfg: Any, path: str) -> dict[str, Any]:
    """The student of a run with ``advisor.amortize`` (its last checkpoint) on every state."""
    from uavlae.checkpoint import load_checkpoint
    from uavlae.policies.student import Student, encode, make_student_config

    ckpt, file = load_checkpoint(path)
    adv = (ckpt.get("collector") or {}).get("policy_extra", {}).get("advisor")
    if not isinstance(adv, dict) or "student" not in adv:
        raise SystemExit(f"{file} holds no student: train with +exp=sac_llm_amortized (or advisor.amortize=true)")
    cfg = make_student_config(ckpt["config"]["advisor"]["student"])
    student = Student(cfg)
    student.load_state_dict(adv["student"])
    limits = WorldLimits.from_env_config(env_cfg)
    states = advisor_states_from_tensordict(TensorDict({"state": state}, batch_size=state.batch_size),
                                            list(range(state.batch_size[0])), limits)
    n = len(states)
    t0 = time.perf_counter()
    dcu, ents, _ = encode(states, cfg, ckpt["config"]["llm"]["observation"])
    mean, spread = student.predict(dcu, ents)
    per = (time.perf_counter() - t0) / max(n, 1)
    about = {"checkpoint": str(file), "frames": int(ckpt["counters"]["frames"]), "answers_learned": student.answers,
             "updates": student.updates, "llm_rows": int(adv["llm_rows"]), "unsure": cfg.unsure,
             "spread_mean": float(spread.mean()), "spread_above_unsure": float((spread > cfg.unsure).float().mean()),
             # per state: would the student have answered it itself in a run (members within `unsure`)?
             "sure": (spread <= cfg.unsure).tolist()}
    return {"action": mean.clamp(-1, 1), "valid": [True] * n, "latency": [per] * n, "student": about}


def timed(fn: Callable[[], torch.Tensor], n: int) -> dict[str, Any]:
    t0 = time.perf_counter()
    action = fn()
    per = (time.perf_counter() - t0) / max(n, 1)
    return {"action": action, "valid": [True] * n, "latency": [per] * n}


def answers(name: str, state: TensorDict, env: UAVEnv, args: argparse.Namespace) -> dict[str, Any]:
    n, env_cfg = state.batch_size[0], env.cfg
    if name in LLM_VARIANTS:
        cfg = make_llm_config(args.llm, cache_mode="off", **LLM_VARIANTS[name])
        return llm_answers(state, env_cfg, cfg)
    if name == "endpoint":
        if not args.endpoint:
            raise SystemExit("advisor 'endpoint' needs --endpoint PRESET_OR_YAML (an OpenAI-compatible server)")
        return llm_answers(state, env_cfg, make_llm_config(args.endpoint, cache_mode="off"))
    if name == "heuristic":
        h = HeuristicPolicy(env_cfg)
        return timed(lambda: h.act(state), n)
    if name == "hover":
        return timed(lambda: torch.zeros(n, 2), n)
    if name == "random":  # uniform in the disc |v| <= v_max
        g = torch.Generator().manual_seed(args.seed)

        def draw() -> torch.Tensor:
            r, th = torch.rand(n, generator=g).sqrt(), torch.rand(n, generator=g) * 2 * math.pi
            return torch.stack([r * th.cos(), r * th.sin()], -1)
        return timed(draw, n)
    if name == "student":
        if not args.student:
            raise SystemExit("advisor 'student' needs --student RUN_DIR (a run trained with advisor.amortize=true)")
        return student_answers(state, env_cfg, args.student)
    if name == "actor":
        if not args.actor:
            raise SystemExit("advisor 'actor' needs --actor FILE.pt2 (written by python -m uavlae.export)")
        from uavlae.fly import load_actor

        actor, _ = load_actor(args.actor)
        obs = env.layout.build(dict(state.items()))
        with torch.no_grad():
            return timed(lambda: actor(obs).reshape(n, 2).clamp(-1, 1), n)
    raise SystemExit(f"unknown advisor {name!r}; one of {list(ADVISORS)}")


# ------------------------------------------------------------------ summary and table
def summarise(per_state: dict[str, list[float]], idx: list[int]) -> dict[str, float]:
    out: dict[str, float] = {"n": len(idx)}
    for k, v in per_state.items():
        vals = [v[i] for i in idx]
        if k == "latency":
            s = sorted(vals)
            out["latency_p50_s"] = s[len(s) // 2]
            out["latency_p95_s"] = s[min(len(s) - 1, int(0.95 * len(s)))]
        elif k in ("valid", "prompt_tokens", "cached_prompt_tokens", "completion_tokens", "calls",
                   "paper_example") or k.endswith(("_1", "_H", "_m")):
            out[k] = sum(float(x) for x in vals) / len(vals)
    return out


def paper_example_flags(actions: list[list[float]], v_max: float) -> list[float]:
    """1.0 where the answer is the velocity of the paper's example answer (4.2, 1.6) m/s."""
    ex = PAPER_EXAMPLE_VELOCITY
    return [float(abs(a[0] * v_max - ex[0]) < 1e-3 and abs(a[1] * v_max - ex[1]) < 1e-3) for a in actions]


def top_answer_share(actions: list[list[float]]) -> float:
    """The fraction of the states given the most common answer (1.0: one answer for all)."""
    return Counter(tuple(a) for a in actions).most_common(1)[0][1] / len(actions) if actions else math.nan


COLUMNS = [("valid", "valid", "{:.2f}"), ("any_violation_1", "viol. 1 slot", "{:.3f}"),
           ("any_violation_H", "viol. H slots", "{:.3f}"), ("bz_collision_H", "BZ", "{:.3f}"),
           ("nfz_entry_H", "NFZ", "{:.3f}"), ("ou_collision_H", "OU", "{:.3f}"),
           ("rz_speeding_H", "RZ speed", "{:.3f}"), ("boundary_exit_H", "boundary", "{:.3f}"),
           ("progress_1_m", "progress 1 (m)", "{:+.2f}"), ("progress_H_m", "progress H (m)", "{:+.2f}"),
           ("paper_example", "= example", "{:.3f}"), ("top_answer", "top answer", "{:.3f}"),
           ("calls", "calls", "{:.2f}"), ("latency_p50_s", "p50 s", "{:.3g}"), ("prompt_tokens", "prompt tok", "{:.0f}"),
           ("cached_prompt_tokens", "of them cached", "{:.0f}"), ("completion_tokens", "compl. tok", "{:.0f}")]


def paired(a: list[float], b: list[float], seed: int = 0, draws: int = 2000) -> tuple[float, float, float]:
    """Mean of b - a over the same states and its 95% bootstrap interval (states resampled)."""
    d = torch.tensor(b, dtype=torch.float64) - torch.tensor(a, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(0, d.numel(), (draws, d.numel()), generator=g)
    means = d[idx].mean(1).sort().values
    return float(d.mean()), float(means[int(0.025 * draws)]), float(means[int(0.975 * draws) - 1])


def table(results: dict[str, Any]) -> str:
    adv = results["advisors"]
    hold = results["hold"]
    lines = [f"# Advice quality on {results['states']['n']} saved triggered states "
             f"({results['states']['kinds']}; H = {hold} slots held)", "",
             "Fractions of states with the event (H: within the held slots); progress toward the "
             "current target in metres; `= example`: answers that are the velocity of the paper's example "
             "answer (4.2, 1.6) m/s; `top answer`: the share of the most common answer; "
             "`python benchmarks/advice_quality.py` (see its docstring). The "
             "latencies here come from runs beside other jobs; the timed ones are in "
             "`benchmarks/llm_call_breakdown.json`.", ""]
    sizes = sorted({a["n_states"] for a in adv.values()}, reverse=True)
    for size in sizes:
        names = [k for k, a in adv.items() if a["n_states"] >= size]
        lines += [f"## The first {size} states", "",
                  "| advisor | " + " | ".join(c[1] for c in COLUMNS) + " |",
                  "|---" * (len(COLUMNS) + 1) + "|"]
        for name in names:
            s = summarise(adv[name]["per_state"], list(range(size)))
            s["top_answer"] = top_answer_share(adv[name]["actions"][:size])
            cells = [fmt.format(s[k]) if k in s and not (isinstance(s[k], float) and math.isnan(s[k])) else "-"
                     for k, _, fmt in COLUMNS]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("")
    for ref_name, what in (("llm", "the default"), ("llm_verbose", "the earlier default"),
                           ("llm_paper_example", "the prompt each variant changes one setting of")):
        if ref_name not in adv:
            continue
        lines += [f"## Each LLM prompt against {what} (`{ref_name}`), state by state", "",
                  f"Mean difference (other - {ref_name}) over the states both answered, with a 95% bootstrap "
                  "interval; a cheaper prompt must not be worse: violations not higher, progress not lower.", "",
                  "| advisor | states | Δ viol. H slots | Δ progress H (m) | answers that differ | mean gap (m/s) |",
                  "|---|---|---|---|---|---|"]
        ref = adv[ref_name]
        for name, a in adv.items():
            if name == ref_name or not (name.startswith("llm") or name == "student"):
                continue
            n = min(a["n_states"], ref["n_states"])
            cells = []
            for key in ("any_violation_H", "progress_H_m"):
                m, lo, hi = paired(ref["per_state"][key][:n], a["per_state"][key][:n])
                cells.append(f"{m:+.3f} [{lo:+.3f}, {hi:+.3f}]")
            differ = sum(x != y for x, y in zip(ref["actions"][:n], a["actions"][:n]))
            gap = sum(math.dist(x, y) for x, y in zip(ref["actions"][:n], a["actions"][:n])) / n * results["v_max"]
            lines.append(f"| {name} | {n} | " + " | ".join(cells) + f" | {differ} | {gap:.2f} |")
            sure = (a.get("student") or {}).get("sure")
            if sure and any(sure[:n]):  # where the student would have answered in a run, not asked the LLM
                idx = [i for i in range(n) if sure[i]]
                cells = []
                for key in ("any_violation_H", "progress_H_m"):
                    m, lo, hi = paired([ref["per_state"][key][i] for i in idx], [a["per_state"][key][i] for i in idx])
                    cells.append(f"{m:+.3f} [{lo:+.3f}, {hi:+.3f}]")
                gap = sum(math.dist(ref["actions"][i], a["actions"][i]) for i in idx) / len(idx) * results["v_max"]
                lines.append(f"| {name} where sure | {len(idx)} | " + " | ".join(cells)
                             + f" | {sum(ref['actions'][i] != a['actions'][i] for i in idx)} | {gap:.2f} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--collect", action="store_true", help="build the saved state set and exit")
    ap.add_argument("--states", default=str(STATES))
    ap.add_argument("--n-states", type=int, default=200, help="--collect: states to keep")
    ap.add_argument("--rollout-batch", type=int, default=32)
    ap.add_argument("--rollout-steps", type=int, default=200)
    ap.add_argument("--d-th", type=float, default=15.0, help="the trigger's threshold (m), as uavlae/conf/advisor/llm.yaml")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--advisors", nargs="+", default=["heuristic", "hover", "random", "llm"], choices=ADVISORS)
    ap.add_argument("--n", type=int, default=None, help="score only the first N states (default: all)")
    ap.add_argument("--hold", type=int, default=3, help="slots the answer is held (scored within them)")
    ap.add_argument("--llm", default="local", help="LLM preset or YAML for the llm* advisors")
    ap.add_argument("--endpoint", default=None, help="preset or YAML of an OpenAI-compatible endpoint")
    ap.add_argument("--actor", default=None, help="an actor exported by python -m uavlae.export")
    ap.add_argument("--student", default=None, help="a run (or checkpoint) trained with advisor.amortize=true")
    ap.add_argument("--rescore", action="store_true",
                    help="score every stored advisor again from its stored answers (no advisor is asked)")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--table", default=str(TABLE))
    args = ap.parse_args()
    if args.collect:
        collect(args)
        return
    path = Path(args.states)
    if not path.is_file():
        raise SystemExit(f"no saved states at {path}: run `python benchmarks/advice_quality.py --collect` first")
    full, meta, digest = load_states(path)
    if args.n is not None and not 1 <= args.n <= full.batch_size[0]:
        raise SystemExit(f"--n must be in [1, {full.batch_size[0]}], got {args.n}")
    state = full[: args.n] if args.n is not None else full
    n = state.batch_size[0]
    # always the whole set in one batch: the env's draws for a state do not depend on --n
    env = UAVEnv(make_env_config(None), batch_size=full.batch_size[0], seed=args.seed)
    out_path = Path(args.out)
    import json

    results = json.loads(out_path.read_text()) if out_path.is_file() else {}
    if results.get("states", {}).get("sha256_16") != digest or results.get("hold") != args.hold:
        results = {}  # another state set or hold: start afresh
    kinds = {k: meta["kind"].count(k) for k in KINDS}
    results.update({"benchmark": "advice_quality", "hold": args.hold, "seed": args.seed,
                    "states": {"path": str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path),
                               "n": len(meta["kind"]), "kinds": kinds, "sha256_16": digest, "d_th": meta["d_th"]},
                    "machine": describe_machine(), "v_max": make_env_config(None).motion.v_max})
    results.setdefault("advisors", {})
    if args.rescore:
        for name, entry in results["advisors"].items():
            k = entry["n_states"]
            sc = score_first(env, full, torch.tensor(entry["actions"]), args.hold, args.seed)
            entry["per_state"].update({key: v.tolist() for key, v in sc.items()})
            entry["per_state"]["paper_example"] = paper_example_flags(entry["actions"], env.cfg.motion.v_max)
            entry["summary"] = {**summarise(entry["per_state"], list(range(k))),
                                "top_answer": top_answer_share(entry["actions"])}
            entry["rescored"] = portable("python benchmarks/advice_quality.py " + " ".join(sys.argv[1:]), ROOT)
        dump_json(out_path, results)
        args.advisors = []
    for name in args.advisors:
        print(f"{name}: answering {n} states", flush=True)
        t0 = time.perf_counter()
        ans = answers(name, state, env, args)
        sc = score_first(env, full, ans["action"], args.hold, args.seed)
        per_state = {k: v.tolist() for k, v in sc.items()}
        per_state.update({k: list(ans[k]) for k in ("valid", "latency", "prompt_tokens", "cached_prompt_tokens",
                                                     "completion_tokens", "calls") if k in ans})
        actions = [[round(x, 4) for x in a] for a in ans["action"].tolist()]
        per_state["paper_example"] = paper_example_flags(actions, env.cfg.motion.v_max)
        entry = {"n_states": n, "wall_s": round(time.perf_counter() - t0, 1),
                 "command": portable("python benchmarks/advice_quality.py " + " ".join(sys.argv[1:]), ROOT),
                 "summary": summarise(per_state, list(range(n))), "per_state": per_state,
                 "llm_overrides": LLM_VARIANTS.get(name), "rejected": ans.get("rejected"), "actions": actions}
        if "student" in ans:
            entry["student"] = ans["student"]
        entry["summary"]["top_answer"] = top_answer_share(actions)
        results["advisors"][name] = entry
        # after each advisor (a long run keeps what it finished), over what another run beside
        # this one wrote there meanwhile
        now = json.loads(out_path.read_text()) if out_path.is_file() else {}
        if now.get("states", {}).get("sha256_16") == digest and now.get("hold") == args.hold:
            results["advisors"] = {**now.get("advisors", {}), name: entry}
        dump_json(out_path, results)
        s = entry["summary"]
        print(f"  {name}: valid {s['valid']:.2f}, violation(H) {s['any_violation_H']:.3f}, "
              f"progress(H) {s['progress_H_m']:+.2f} m, = example {s['paper_example']:.3f}, "
              f"p50 {s['latency_p50_s']:.3g} s", flush=True)
    text = table(results) + "\n"
    atomic_write(args.table, lambda fh: fh.write(text.encode("utf-8")))
    print(table(results))


if __name__ == "__main__":
    main()
