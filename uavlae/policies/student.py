"""The student advisor: the LLM at every trigger, at a fraction of the calls (beyond the paper,
off by default: ``advisor.amortize``).

A small network, trained online on the LLM's validated answers, answers the triggered rows it
is sure of; the LLM answers the rest. Per triggered row, the LLM is asked when

- the student has fewer than ``min_answers`` answers to learn from (the first steps only);
- the student is unsure: its ensemble's members disagree by more than ``unsure`` (the RMS
  distance of the members' velocities from their mean, in action units, v / v_max);
- the state is unlike those answered so far: its *situation* (which obstacle is nearest, where
  it lies relative to the way to the target, how close, whether the DCU flies faster than the
  RZ limit) has fewer than ``novel_min`` answers;
- the row is drawn for an audit (probability ``audit_fraction``, the module's own seeded
  generator): the LLM answers it whatever the student thinks, and the gap between the two
  measures the student's fidelity on an unbiased sample of rows;

and never once ``max_llm_rows`` rows have been asked in the run (then the student answers
every row). With ``max_llm_share`` the unsure and novel rows are asked only while the LLM's share
of the triggered rows stays under it (a credit earned per triggered row), novel and least sure
first: a spending rate, where ``max_llm_rows`` is a total; ``share_allowance`` rows of credit
are there from the start, so the student asks freely while it knows least, then at the rate. The LLM's answer is executed on the
rows it answers (``action_source`` LLM), the student's mean on the others (``action_source``
STUDENT).

The student sees what the prompt shows the LLM and no more: the rectangles of the zones, the
GEs with remaining data, the visible OUs, the landing area and the DCU's position and velocity,
each rounded as the prompt writes it (:func:`shown_state`); its features are functions of those
numbers (directions and distances from the DCU, which the prompt's numbers determine).

Deterministic: the student trains in the caller's thread when a step's answers are merged
(``result()``), on the answers in the order they were asked, with its own seeded generators,
so a run that replays its answers from the cache (``llm.cache_mode=replay_only``) trains the
same student and asks the same rows. Its whole state (network, optimiser, answers kept,
generators, counters) is in :meth:`AmortizedAdvisor.state_dict`, checkpointed with the run.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import torch
from pydantic import Field, model_validator
from tensordict import TensorDictBase
from torch import Tensor, nn

from uavlae.llm import GroundEquipment, OtherUAV
from uavlae.policies.advisor import LLM, STUDENT, Advisor, Handle, LLMAdvisorAdapter, Price
from uavlae.validation import StrictModel, parse_model

ENTITY_TYPES = ("bz", "nfz", "rz", "ge", "ou")
N_DCU = 8  # x/X, y/Y, vx/v_max, vy/v_max, in an RZ, landing centre dx/X, dy/Y, faster than v_limit
# type one-hot, direction to its nearest point, distance/X, exp(-distance/near_m), inside,
# centre relative/X, half sizes/X, remaining data, velocity/v_max
N_ENTITY = len(ENTITY_TYPES) + 2 + 1 + 1 + 1 + 2 + 2 + 1 + 2
SITUATION_KINDS = ("bz", "nfz", "rz", "ou", "none")
SECTORS = 8  # the bearing of the nearest obstacle relative to the bearing of the target
BANDS = 3  # inside it, within close_m, beyond
N_CELLS = len(SITUATION_KINDS) * SECTORS * BANDS * 2
# why a row went to the LLM (counted in this order: a row counts once, for its first reason)
REASONS = ("warmup", "unsure", "novel", "audit")


class StudentConfig(StrictModel):
    """``advisor.student``: the student advisor's numbers (used with ``advisor.amortize``)."""

    members: int = Field(5, ge=2)  # ensemble members: their disagreement is the uncertainty
    hidden: int = Field(64, ge=4)
    lr: float = Field(3e-3, gt=0)  # a small net learning from few answers: faster than SAC's
    batch_size: int = Field(64, ge=1)
    updates_per_answer: float = Field(4.0, ge=0)  # gradient steps per new validated answer
    capacity: int = Field(20000, ge=1)  # answers kept to learn from (the oldest go first)
    min_answers: int = Field(64, ge=1)  # the LLM answers every row until it has given this many
    unsure: float = Field(0.1, gt=0)  # members' RMS spread (action units) above which the LLM is asked
    novel_min: int = Field(2, ge=0)  # answers a situation needs before the student answers in it (0: off)
    audit_fraction: float = Field(0.01, ge=0, le=1)  # rows the LLM answers anyway, drawn at random
    max_llm_rows: int | None = Field(None, ge=1)  # rows the LLM may answer in the run (null: no cap)
    # after the warm-up, the LLM's share of the triggered rows at most (null: no bound): each
    # triggered row earns this much credit (at most share_burst kept), each row the LLM answers
    # spends one; unsure and novel rows are asked, most novel then least sure first, while credit
    # lasts. Audits are always asked (they spend credit too), so the share is max(this, audit_fraction)
    max_llm_share: float | None = Field(None, gt=0, le=1)
    share_burst: float = Field(64.0, ge=1)
    # rows of credit the share starts with (used with max_llm_share): what the student may ask
    # beyond the rate early on, while it knows least; above share_burst no credit accrues until
    # the allowance is spent below it
    share_allowance: int = Field(0, ge=0)
    near_m: float = Field(10.0, gt=0)  # length scale of the near-field feature exp(-d / near_m)
    close_m: float = Field(5.0, gt=0)  # a situation's distance bands: inside, within close_m, beyond

    @model_validator(mode="after")
    def _check(self) -> "StudentConfig":
        if self.capacity < self.min_answers:
            raise ValueError(f"advisor.student.capacity={self.capacity} keeps fewer answers than min_answers="
                             f"{self.min_answers}: the student would never answer")
        if self.max_llm_rows is not None and self.max_llm_rows < self.min_answers:
            raise ValueError(f"advisor.student.max_llm_rows={self.max_llm_rows} is below min_answers="
                             f"{self.min_answers}: the student would answer before it has learned anything")
        return self


def make_student_config(cfg: Any) -> StudentConfig:
    return parse_model(StudentConfig, cfg, prefix="advisor.student", title="student")


# ---------------------------------------------------------------------------- what the prompt shows

# decimals the observation writes each number with (uavlae/llm/prompt.py): position, velocity,
# GE position, GE data, OU position, OU velocity, zone corners
_DECIMALS = {"compact": (0, 1, 0, 1, 0, 1, 0), "verbose": (1, 1, 0, 2, 1, 1, 0)}


def _r(v: float, nd: int) -> float:
    return float(f"{v:.{nd}f}") if math.isfinite(v) else v  # the prompt's own rounding


def shown_state(s: Any, observation: str = "compact") -> Any:
    """``s`` with every number the student reads rounded as the observation writes it."""
    p, v, gp, gd, op, ov, z = _DECIMALS[observation]
    rect = lambda r: tuple(_r(c, z) for c in r)  # noqa: E731
    return replace(
        s, position=(_r(s.position[0], p), _r(s.position[1], p)), velocity=(_r(s.velocity[0], v), _r(s.velocity[1], v)),
        ges=tuple(GroundEquipment(_r(g.x, gp), _r(g.y, gp), _r(g.remaining, gd)) for g in s.ges),
        ous=tuple(OtherUAV(_r(o.x, op), _r(o.y, op), _r(o.vx, ov), _r(o.vy, ov), o.distance)
                  for o in s.ous if o.distance <= s.limits.perception_radius),
        bz=tuple(rect(r) for r in s.bz), nfz=tuple(rect(r) for r in s.nfz), rz=tuple(rect(r) for r in s.rz))


def _nearest_point(r: Sequence[float], x: float, y: float) -> tuple[float, float]:
    return min(max(x, r[0]), r[2]), min(max(y, r[1]), r[3])


def encode(states: Sequence[Any], cfg: StudentConfig, observation: str = "compact"
           ) -> tuple[Tensor, list[Tensor], Tensor]:
    """The student's input: ``dcu [n, N_DCU]``, one ``[k_i, N_ENTITY]`` tensor of entities per
    state (its zones, GEs with data and visible OUs), and each state's situation cell ``[n]``."""
    dcu, ents, cells = [], [], []
    for s0 in states:
        s = shown_state(s0, observation)
        lim = s.limits
        X, vm = max(lim.x_size, lim.y_size), lim.v_max
        x, y = s.position
        lx, ly = (lim.landing[0] + lim.landing[2]) / 2, (lim.landing[1] + lim.landing[3]) / 2
        speed = math.hypot(*s.velocity)
        fast = speed > lim.v_limit
        dcu.append([x / lim.x_size, y / lim.y_size, s.velocity[0] / vm, s.velocity[1] / vm, float(s.in_rz),
                    (lx - x) / X, (ly - y) / X, float(fast)])
        rows = []
        nearest: tuple[float, str, float, float] = (math.inf, "none", 0.0, 0.0)  # distance, kind, dx, dy

        def add(kind: str, px: float, py: float, centre: tuple[float, float], half: tuple[float, float],
                remaining: float = 0.0, vel: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float, float]:
            dx, dy = px - x, py - y
            d = math.hypot(dx, dy)
            ux, uy = (dx / d, dy / d) if d > 0 else (0.0, 0.0)
            onehot = [float(kind == t) for t in ENTITY_TYPES]
            rows.append(onehot + [ux, uy, d / X, math.exp(-d / cfg.near_m), float(d == 0.0),
                                  (centre[0] - x) / X, (centre[1] - y) / X, half[0] / X, half[1] / X,
                                  remaining, vel[0] / vm, vel[1] / vm])
            return d, dx, dy

        for kind, zones in (("bz", s.bz), ("nfz", s.nfz), ("rz", s.rz)):
            for r in zones:
                px, py = _nearest_point(r, x, y)
                centre, half = ((r[0] + r[2]) / 2, (r[1] + r[3]) / 2), ((r[2] - r[0]) / 2, (r[3] - r[1]) / 2)
                d, dx, dy = add(kind, px, py, centre, half)
                if d < nearest[0]:
                    nearest = (d, kind, dx, dy)
        for g in s.ges:
            add("ge", g.x, g.y, (g.x, g.y), (0.0, 0.0), remaining=g.remaining)
        for o in s.ous:
            d, dx, dy = add("ou", o.x, o.y, (o.x, o.y), (0.0, 0.0), vel=(o.vx, o.vy))
            if d < nearest[0]:
                nearest = (d, "ou", dx, dy)
        ents.append(torch.tensor(rows, dtype=torch.float32).reshape(-1, N_ENTITY))
        # the target: the nearest GE with data as the prompt lists them, else the landing area
        tx, ty = min(((g.x, g.y) for g in s.ges), key=lambda p: math.hypot(p[0] - x, p[1] - y), default=(lx, ly))
        cells.append(_cell(nearest, math.atan2(ty - y, tx - x), fast, cfg.close_m))
    return torch.tensor(dcu, dtype=torch.float32).reshape(-1, N_DCU), ents, torch.tensor(cells, dtype=torch.int64)


def _cell(nearest: tuple[float, str, float, float], target_bearing: float, fast: bool, close_m: float) -> int:
    d, kind, dx, dy = nearest
    if kind == "none":
        sector, band = 0, BANDS - 1
    else:
        rel = (math.atan2(dy, dx) - target_bearing) % (2 * math.pi) if d > 0 else 0.0
        sector = int(rel / (2 * math.pi / SECTORS)) % SECTORS
        band = 0 if d == 0.0 else (1 if d <= close_m else 2)
    return ((SITUATION_KINDS.index(kind) * SECTORS + sector) * BANDS + band) * 2 + int(fast)


def _pad(ents: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """``[n, K, N_ENTITY]`` entities and their ``[n, K]`` mask (K: the most any state has, >= 1)."""
    lengths = torch.tensor([e.shape[0] for e in ents], dtype=torch.int64)
    out = nn.utils.rnn.pad_sequence([*ents, torch.zeros(1, N_ENTITY)], batch_first=True)[: len(ents)]
    return out, torch.arange(out.shape[1]) < lengths[:, None]


# ---------------------------------------------------------------------------- the network


class _EnsembleLinear(nn.Module):
    """``members`` independent linear layers applied at once: ``[E, M, i] -> [E, M, o]``."""

    def __init__(self, members: int, i: int, o: int, generator: torch.Generator):
        super().__init__()
        bound = 1.0 / math.sqrt(i)  # torch's default Linear initialisation, from our own generator
        self.weight = nn.Parameter((torch.rand(members, i, o, generator=generator) * 2 - 1) * bound)
        self.bias = nn.Parameter((torch.rand(members, 1, o, generator=generator) * 2 - 1) * bound)

    def forward(self, x: Tensor) -> Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class StudentNet(nn.Module):
    """An ensemble of small set networks: each entity through a shared MLP, pooled per entity
    type by attention (a learned score, softmax over that type's entities: it can pick the
    nearest GE or obstacle, as an answer often turns on one), with the DCU's own features through
    another MLP, then a head to a velocity inside the disc |v| <= v_max (action units)."""

    def __init__(self, members: int, hidden: int, generator: torch.Generator):
        super().__init__()
        E, H, T = members, hidden, len(ENTITY_TYPES)
        self.members = E
        self.entity = nn.ModuleList([_EnsembleLinear(E, N_ENTITY, H, generator), _EnsembleLinear(E, H, H, generator)])
        self.score = _EnsembleLinear(E, H, T, generator)  # one attention score per entity type
        self.dcu = _EnsembleLinear(E, N_DCU, H, generator)
        self.head = nn.ModuleList([_EnsembleLinear(E, H * (T + 1), H, generator),
                                   _EnsembleLinear(E, H, H, generator), _EnsembleLinear(E, H, 2, generator)])

    def forward(self, dcu: Tensor, ent: Tensor, mask: Tensor) -> Tensor:
        """``dcu [E, n, N_DCU]``, ``ent [E, n, K, N_ENTITY]``, ``mask [E, n, K]`` -> ``[E, n, 2]``."""
        E, n, K, _ = ent.shape
        T = len(ENTITY_TYPES)
        h = ent.reshape(E, n * K, N_ENTITY)
        h = torch.relu(self.entity[1](torch.relu(self.entity[0](h))))  # [E, nK, H]
        member = (ent[..., :T] > 0.5) & mask[..., None]  # [E, n, K, T]: entity k is of type t
        score = self.score(h).reshape(E, n, K, T).masked_fill(~member, -1e9)
        w = torch.softmax(score, dim=2) * member  # a type with no entity pools to zeros
        pooled = torch.einsum("enkt,enkh->enth", w, h.reshape(E, n, K, -1)).reshape(E, n, -1)
        z = torch.cat([pooled, torch.relu(self.dcu(dcu))], -1)
        z = torch.relu(self.head[1](torch.relu(self.head[0](z))))
        o = self.head[2](z)
        norm = o.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        return o * (torch.tanh(norm) / norm)  # inside the unit disc: |v| < v_max, as a validated answer


class Student:
    """The ensemble, its optimiser and the answers it learns from (a ring of ``capacity``)."""

    def __init__(self, cfg: StudentConfig, seed: int = 0):
        self.cfg = cfg
        self.generator = torch.Generator().manual_seed(int(seed))
        self.net = StudentNet(cfg.members, cfg.hidden, self.generator)
        self.optim = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        self.dcu: list[Tensor] = []  # the ring of answers: the DCU's features, entities, target action
        self.ent: list[Tensor] = []
        self.target: list[Tensor] = []
        self.next = 0  # where the next answer goes once the ring is full
        self.cell_counts = torch.zeros(N_CELLS, dtype=torch.int64)
        self.answers = 0  # validated answers learned from in the run
        self.updates = 0
        self.debt = 0.0  # gradient steps owed (fractions carried)
        self.last_loss = math.nan

    def __len__(self) -> int:
        return len(self.target)

    @torch.no_grad()
    def predict(self, dcu: Tensor, ents: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
        """``(mean [n, 2], spread [n])``: the members' mean action and their RMS distance from it."""
        if not len(ents):
            return torch.zeros(0, 2), torch.zeros(0)
        ent, mask = _pad(ents)
        E = self.cfg.members
        out = self.net(dcu.expand(E, *dcu.shape), ent.expand(E, *ent.shape), mask.expand(E, *mask.shape))
        mean = out.mean(0)
        spread = (out - mean).square().sum(-1).mean(0).sqrt()
        return mean, spread

    def learn(self, dcu: Tensor, ents: Sequence[Tensor], cells: Tensor, target: Tensor) -> None:
        """Keep these answers (``target``: actions, v / v_max) and take the gradient steps they earn."""
        for i in range(target.shape[0]):
            item = (dcu[i].clone(), ents[i].clone(), target[i].clone())
            if len(self.target) < self.cfg.capacity:
                self.dcu.append(item[0]), self.ent.append(item[1]), self.target.append(item[2])
            else:
                self.dcu[self.next], self.ent[self.next], self.target[self.next] = item
                self.next = (self.next + 1) % self.cfg.capacity
        self.cell_counts += torch.bincount(cells, minlength=N_CELLS)
        self.answers += int(target.shape[0])
        self.debt += self.cfg.updates_per_answer * target.shape[0]
        steps, self.debt = int(self.debt), self.debt - int(self.debt)
        for _ in range(steps):
            self._step()

    def _step(self) -> None:
        E, bs, n = self.cfg.members, self.cfg.batch_size, len(self.target)
        # each member its own draw with replacement: the members differ by their data too
        idx = torch.randint(0, n, (E * bs,), generator=self.generator).tolist()
        ent, mask = _pad([self.ent[i] for i in idx])
        dcu = torch.stack([self.dcu[i] for i in idx]).reshape(E, bs, N_DCU)
        target = torch.stack([self.target[i] for i in idx]).reshape(E, bs, 2)
        with torch.enable_grad():
            out = self.net(dcu, ent.reshape(E, bs, *ent.shape[1:]), mask.reshape(E, bs, -1))
            loss = (out - target).square().sum(-1).mean()
            self.optim.zero_grad(set_to_none=True)
            loss.backward()
            self.optim.step()
        self.updates += 1
        self.last_loss = float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        """A copy: training after this call does not change it (plain tensors and containers)."""
        return {"net": {k: v.detach().clone() for k, v in self.net.state_dict().items()},
                "optim": copy.deepcopy(self.optim.state_dict()), "generator": self.generator.get_state(),
                "dcu": list(self.dcu), "ent": list(self.ent), "target": list(self.target),  # never written in place
                "next": self.next, "cell_counts": self.cell_counts.clone(), "answers": self.answers,
                "updates": self.updates, "debt": self.debt}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.optim.load_state_dict(copy.deepcopy(state["optim"]))
        self.generator.set_state(state["generator"])
        self.dcu, self.ent, self.target = list(state["dcu"]), list(state["ent"]), list(state["target"])
        self.next, self.answers, self.updates = int(state["next"]), int(state["answers"]), int(state["updates"])
        self.cell_counts = state["cell_counts"].clone()
        self.debt = float(state["debt"])


# ---------------------------------------------------------------------------- the advisor


class AmortizedAdvisor(Advisor):
    """The student and the LLM behind the advisor contract (module docstring).

    Args:
        llm: a :class:`uavlae.policies.advisor.LLMAdvisorAdapter` (any endpoint of the ``llm`` group).
        cfg: the student's numbers (``advisor.student``).
        seed: seeds the student (initialisation, minibatches) and, apart, the audit draws.
    """

    source = LLM  # result() gives each row's own source: LLM or STUDENT
    asks_llm = True

    def __init__(self, llm: LLMAdvisorAdapter, cfg: StudentConfig | Mapping[str, Any] | None = None, seed: int = 0):
        self.llm = llm
        self.cfg = cfg if isinstance(cfg, StudentConfig) else make_student_config(cfg)
        self.observation = llm.observation  # the student sees what the prompt shows the LLM
        self.student = Student(self.cfg, seed=seed)
        self.audit_generator = torch.Generator().manual_seed(int(seed) + 1)
        self.llm_rows = 0  # rows sent to the LLM in the run (max_llm_rows)
        self.credit = float(self.cfg.share_allowance)  # rows the LLM may still answer under max_llm_share
        self.reset_counts()

    def reset_counts(self) -> None:
        self.counts: dict[str, float] = {"rows": 0, "llm_rows": 0, "student_rows": 0,
                                         **{f"asked_{r}": 0 for r in REASONS},
                                         # the student's velocity error (m/s) against the LLM's answer:
                                         # on the audited rows it would have answered (a random sample of
                                         # the rows it answers) and on every row the LLM answered after warm-up
                                         "audit_err_rows": 0, "audit_err_sum": 0.0, "llm_err_rows": 0,
                                         "llm_err_sum": 0.0, "updates": 0, "train_s": 0.0}

    def advise(self, td_rows: TensorDictBase, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return self.start(td_rows, rows).result()

    def start(self, td_rows: TensorDictBase, rows: Tensor) -> "_AmortizedHandle":
        """Decide per row who answers; send the LLM's rows at once; the student's are answered."""
        states = self.llm.states(td_rows)
        n = len(states)
        dcu, ents, cells = encode(states, self.cfg, self.observation)
        audit = torch.rand(n, generator=self.audit_generator) < self.cfg.audit_fraction  # drawn for every row
        mean, spread = self.student.predict(dcu, ents)
        c = self.cfg
        warm = len(self.student) < c.min_answers
        reasons = torch.stack([
            torch.full((n,), warm, dtype=torch.bool),
            spread > c.unsure,
            self.student.cell_counts[cells] < c.novel_min,
            audit,
        ])  # [len(REASONS), n]
        ask = reasons.any(0)
        if c.max_llm_share is not None and not warm:
            ask = self._within_share(reasons, spread)
        if c.max_llm_rows is not None:
            ask &= torch.cumsum(ask.long(), 0) <= max(c.max_llm_rows - self.llm_rows, 0)
        asked = ask.nonzero().squeeze(-1)
        first = reasons.long().argmax(0)  # the first reason that holds
        for k, r in enumerate(REASONS):
            self.counts[f"asked_{r}"] += int((ask & (first == k)).sum())
        self.llm_rows += int(asked.numel())
        handle = self.llm.ask([states[i] for i in asked.tolist()]) if asked.numel() else None
        # the audited rows the student would have answered: its fidelity where it acts
        audit_only = audit & ~reasons[:3].any(0)
        return _AmortizedHandle(self, handle, asked, audit_only[asked], mean, dcu, ents, cells, warm)

    def _within_share(self, reasons: Tensor, spread: Tensor) -> Tensor:
        """The rows to ask under ``max_llm_share``: every audit, then unsure and novel rows
        (novel first, then the least sure) while the credit lasts."""
        c = self.cfg
        n = spread.shape[0]
        # accrue up to the burst; a larger credit (the allowance) is spent before any accrues
        self.credit = max(min(self.credit + c.max_llm_share * n, c.share_burst), self.credit)
        audit, want = reasons[3], (reasons[1] | reasons[2]) & ~reasons[3]
        ask = audit.clone()
        room = int(math.floor(self.credit - int(audit.sum())))
        if room > 0 and want.any():
            key = torch.where(reasons[2], math.inf, spread)  # novel first, then by disagreement
            order = sorted(want.nonzero().squeeze(-1).tolist(), key=lambda i: (-float(key[i]), i))
            ask[order[:room]] = True
        self.credit -= int(ask.sum())
        return ask

    def _merge(self, h: "_AmortizedHandle") -> tuple[Tensor, Tensor, Tensor]:
        n = h.mean.shape[0]
        action = h.mean.clone()
        ok = torch.ones(n, dtype=torch.bool)
        source = torch.full((n,), STUDENT, dtype=torch.int64)
        self.counts["rows"] += n
        if h.handle is None:
            self.counts["student_rows"] += n
            return action, ok, source
        answers = h.handle.answers()  # an EndpointError stops the run here
        v_max = self.llm.limits.v_max
        good, targets = [], []
        for j, (i, r) in enumerate(zip(h.asked.tolist(), answers)):
            source[i] = LLM
            if r.ok:
                a = torch.tensor(r.action(v_max), dtype=torch.float32)
                if not h.warm:  # the student's fidelity: how far its own answer lay from the LLM's
                    err = float((h.mean[i] - a).norm()) * v_max
                    self.counts["llm_err_rows"] += 1
                    self.counts["llm_err_sum"] += err
                    if h.audit[j]:
                        self.counts["audit_err_rows"] += 1
                        self.counts["audit_err_sum"] += err
                action[i] = a
                good.append(i)
                targets.append(a)
            else:
                ok[i] = False
        self.counts["llm_rows"] += int(h.asked.numel())
        self.counts["student_rows"] += n - int(h.asked.numel())
        if good:
            t0 = time.perf_counter()
            before = self.student.updates
            self.student.learn(h.dcu[good], [h.ents[i] for i in good], h.cells[good], torch.stack(targets))
            self.counts["updates"] += self.student.updates - before
            self.counts["train_s"] += time.perf_counter() - t0
        return action.clamp(-1.0, 1.0), ok, source

    # -- counters, state, lifecycle -----------------------------------------------------------
    def snapshot(self, reset: bool = False) -> dict[str, float]:
        out = dict(self.llm.snapshot(reset=reset))
        c = self.counts
        out.update({f"student/{k}": v for k, v in c.items()})
        for what in ("audit", "llm"):
            rows = c[f"{what}_err_rows"]
            out[f"student/{what}_err_mps"] = c[f"{what}_err_sum"] / rows if rows else math.nan
        out["student/answers"] = self.student.answers
        out["student/loss"] = self.student.last_loss
        out["student/llm_rows_used"] = self.llm_rows
        if reset:
            self.reset_counts()
        return out

    def latencies(self) -> list[float]:
        return self.llm.latencies()

    def price(self) -> Price | None:
        return self.llm.price()

    def state_dict(self) -> dict[str, Any]:
        return {"llm": self.llm.state_dict(), "student": self.student.state_dict(),
                "audit_generator": self.audit_generator.get_state(), "llm_rows": self.llm_rows,
                "credit": self.credit, "counts": dict(self.counts)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.llm.load_state_dict(state["llm"])
        self.student.load_state_dict(state["student"])
        self.audit_generator.set_state(state["audit_generator"])
        self.llm_rows = int(state["llm_rows"])
        self.credit = float(state["credit"])
        self.counts = dict(state["counts"])

    def close(self) -> None:
        self.llm.close()


class _AmortizedHandle(Handle):
    """One step's answers: the student's now, the LLM's in flight; merged (and learned from) by ``result()``."""

    def __init__(self, owner: AmortizedAdvisor, handle: Any, asked: Tensor, audit: Tensor, mean: Tensor,
                 dcu: Tensor, ents: list[Tensor], cells: Tensor, warm: bool):
        self.owner, self.handle, self.asked, self.audit, self.mean = owner, handle, asked, audit, mean
        self.dcu, self.ents, self.cells, self.warm = dcu, ents, cells, warm
        self.created = time.perf_counter()

    @property
    def done_at(self) -> float | None:
        return self.created if self.handle is None else self.handle.done_at

    @property
    def failures(self) -> Sequence[str]:  # type: ignore[override]
        return () if self.handle is None else self.handle.failures

    def result(self) -> tuple[Tensor, Tensor, Tensor]:
        return self.owner._merge(self)
