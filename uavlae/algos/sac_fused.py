"""SACLoss's gradients written out by hand (``algo.loss_impl: fused``, the default).

torchrl's ``SACLoss`` (v2, no value net) evaluates, per update, the actor on the next
observations (no grad) and on the observations, the target Q nets on (next obs, next action),
and the Q nets twice on the observations: with the replayed action (critic loss) and with the
fresh action and detached parameters (actor loss); autograd then walks all of it back. Each pass
goes through TensorDict modules, ``vmap`` and distribution objects; on one CPU core that
bookkeeping costs more than the arithmetic of the update itself (docs/performance.md).

:class:`FusedSACGrad` returns the same losses and the same gradients for the same parameter
tensors, which it reads from the ``SACLoss`` (the loss keeps owning them, so the optimiser,
the target update, checkpoints and the acting policy are unchanged), as plain tensor ops with
no autograd:

- the first Q layer is split as ``W1 [obs, act] = W1_obs obs + W1_act act``; ``W1_obs obs + b1``
  for every Q net is one batched matmul, shared by the critic pass and the actor pass
  (``SACLoss`` detaches the Q parameters in the actor loss, so the actor pass needs no gradient
  of it);
- every Q layer is a batched matmul over the ``num_qvalue_nets`` dimension, in a contiguous
  ``[n_q, N, h]`` layout;
- backward is written per layer: weight gradients where a loss needs them, input gradients only
  down to where they are needed (the actor loss needs ``dQ/da``, never ``dQ/dobs``);
- the tanh-normal draw and its log-probability follow ``TanhNormal.rsample_and_log_prob``
  (``Normal.log_prob(x) - log|d tanh(x)/dx|``; the Gaussian's ``(x - loc)^2 / 2 var`` is
  ``eps^2 / 2``: same value, same zero gradient), and the two noise tensors are drawn in
  ``SACLoss``'s order (next observations first), so a seeded update draws the same actions.

``tests/test_sac_fused.py`` checks losses and gradients against autograd through ``SACLoss``
(relative error ~1e-7 in float32) for every activation and critic loss, and whole updates.
Supported: what ``make_sac`` builds (MLP actor and critics of any depth, relu / tanh / elu /
silu, ``TanhNormal`` on a box, l2 / l1 / smooth-l1 critic loss, TD(0) targets, SAC v2, no
prioritised weights, no alpha bounds).

With a cloning weight (``clone_weight > 0``, beyond the paper: :mod:`uavlae.algos.sac`), the
actor's gradient also carries the cloning term toward the executed advice,
``w * mean_i m_i * ||tanh(loc_i) - a_i||^2`` (``m_i`` 1 on the rows an advisor acted on), written
out the same way: ``d/dloc = 2 w m (tanh(loc) - a) (1 - tanh(loc)^2) / N``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import inv_softplus
from torchrl.objectives import SACLoss

from uavlae.policies.networks import SCALE_AT_ZERO, SCALE_LB, SCALE_MIN

Layers = list[tuple[torch.Tensor, torch.Tensor]]
_HALF_LOG_2PI = math.log(math.sqrt(2 * math.pi))
_LOG2 = math.log(2.0)
_TANH_LIM = 1.0 - torch.finfo(torch.float32).resolution  # torchrl's safetanh clamp (float32)


def _relu_grad(g: torch.Tensor, z: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    return torch.ops.aten.threshold_backward(g, h, 0.0)


def _tanh_grad(g: torch.Tensor, z: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    return g * (1 - h * h)


def _elu_grad(g: torch.Tensor, z: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    return g * torch.where(z > 0, 1.0, h + 1.0)


def _silu_grad(g: torch.Tensor, z: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    s = torch.sigmoid(z)
    return g * (s * (1 + z * (1 - s)))


# activation -> (forward, backward(grad_out, pre-activation, post-activation))
_ACT: dict[str, tuple[Callable[[torch.Tensor], torch.Tensor], Callable[..., torch.Tensor]]] = {
    "relu": (torch.relu, _relu_grad),
    "tanh": (torch.tanh, _tanh_grad),
    "elu": (F.elu, _elu_grad),
    "silu": (F.silu, _silu_grad),
}
_LOSSES = ("l2", "l1", "smooth_l1")


def _linear_layers(params: TensorDictBase) -> Layers:
    """(weight, bias) of an MLP's linear layers, in order, from its parameter TensorDict."""
    leaves = dict(params.items(True, True))
    weights = sorted((k for k in leaves if k[-1] == "weight"), key=lambda k: [int(p) if p.isdigit() else p for p in k])
    return [(leaves[k], leaves[k[:-1] + ("bias",)]) for k in weights]


class FusedSACGrad:
    """``grads(batch) -> (logs, grads)``: ``SACLoss``'s five outputs and the gradient of
    ``loss_actor + loss_qvalue + loss_alpha`` for :attr:`params` (in that order).

    Built from what ``make_sac`` creates: the ``SACLoss`` (v2, no value network) whose public
    parameter TensorDicts it reads, the nets' ``activation`` and the action box ``low`` /
    ``high`` of the actor's TanhNormal (``None``: [-1, 1]); the scale head is
    ``uavlae.policies.networks``' (``SCALE_AT_ZERO``, ``SCALE_MIN``, ``SCALE_LB``)."""

    def __init__(
        self, loss: SACLoss, activation: str, low: torch.Tensor | None = None, high: torch.Tensor | None = None
    ) -> None:
        if loss.skip_done_states:
            raise ValueError("FusedSACGrad does not implement skip_done_states")
        if loss.loss_function not in _LOSSES:
            raise ValueError(f"loss_function must be one of {list(_LOSSES)}, got {loss.loss_function!r}")
        if activation not in _ACT:
            raise ValueError(f"activation must be one of {sorted(_ACT)}, got {activation!r}")
        if loss.min_log_alpha is not None or loss.max_log_alpha is not None:
            raise ValueError("FusedSACGrad does not implement min_alpha / max_alpha")
        self.loss = loss
        self.act, self.act_grad = _ACT[activation]
        self.loss_function = loss.loss_function
        self.actor_layers = _linear_layers(loss.actor_network_params)
        self.q_layers = _linear_layers(loss.qvalue_network_params)
        self.target_layers = _linear_layers(loss.target_qvalue_network_params)
        if len(self.q_layers) < 2 or len(self.actor_layers) < 2:
            raise ValueError("the actor and the Q nets need at least one hidden layer")
        act_dim = self.actor_layers[-1][0].shape[0] // 2  # the actor outputs loc and scale
        self.obs_dim = self.actor_layers[0][0].shape[1]
        if self.q_layers[0][0].shape[-1] != self.obs_dim + act_dim:
            raise ValueError("the Q nets' input must be [observation, action]")
        self.log_alpha = loss.log_alpha
        # every parameter the optimiser steps, in a fixed order matching grads()' output
        self.params: list[torch.Tensor] = [t for wb in self.actor_layers for t in wb]
        self.params += [t for wb in self.q_layers for t in wb] + [self.log_alpha]
        # the actor's scale head (biased softplus, lower bound) and TanhNormal box
        self.scale_bias = float(inv_softplus(SCALE_AT_ZERO - SCALE_MIN))
        self.scale_min = SCALE_MIN
        self.scale_lb = SCALE_LB
        low = torch.as_tensor(-1.0 if low is None else low)
        high = torch.as_tensor(1.0 if high is None else high)
        self.box: tuple[torch.Tensor, torch.Tensor] | None = None
        if bool((low != -1).any() or (high != 1).any()):
            self.box = ((high + low) / 2, (high - low) / 2)
        self.gamma = float(loss.value_estimator.gamma)
        self.target_entropy = float(loss.target_entropy)

    # -- forward pieces -------------------------------------------------------------------
    def _mlp(self, x: torch.Tensor, layers: Layers) -> tuple[torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
        """Output, each layer's input, each hidden pre-activation."""
        inputs, pre = [], []
        last = len(layers) - 1
        for i, (w, b) in enumerate(layers):
            inputs.append(x)
            x = torch.addmm(b, x, w.t())
            if i < last:
                pre.append(x)
                x = self.act(x)
        return x, inputs, pre

    def _sample(self, obs: torch.Tensor) -> dict[str, torch.Tensor]:
        """Reparameterised tanh-normal action and its log-prob, with what backward needs."""
        out, inputs, pre = self._mlp(obs, self.actor_layers)
        loc, raw = out.chunk(2, -1)
        pre_scale = F.softplus(raw + self.scale_bias) + self.scale_min
        scale = pre_scale.clamp_min(self.scale_lb)
        eps = torch.empty_like(loc).normal_()
        x = loc + eps * scale
        y = x.tanh().clamp_(-_TANH_LIM, _TANH_LIM)  # torchrl's safetanh_noeps
        log_prob = (-0.5 * eps.square() - scale.log() - _HALF_LOG_2PI - 2.0 * (_LOG2 - x - F.softplus(-2.0 * x))).sum(-1)
        action = y
        if self.box is not None:
            action = y * self.box[1] + self.box[0]
            log_prob = log_prob - self.box[1].log().sum()
        return {"action": action, "log_prob": log_prob, "x": x, "y": y, "eps": eps, "raw": raw, "loc": loc,
                "scale": scale, "pre_scale": pre_scale, "inputs": inputs, "pre": pre}  # fmt: skip

    def _q_first(self, obs: torch.Tensor, layers: Layers) -> torch.Tensor:
        """``W1_obs obs + b1`` for every Q net at once: ``[n_q, N, hidden]``."""
        w, b = layers[0]
        return torch.baddbmm(b.unsqueeze(1), obs.expand(w.shape[0], -1, -1), w[..., : self.obs_dim].transpose(1, 2))

    def _q(self, first: torch.Tensor, act: torch.Tensor, layers: Layers) -> tuple[torch.Tensor, list, list]:
        """Q values ``[n_q, N, 1]``, each layer's input ``[n_q, N, .]``, each pre-activation
        (all contiguous: the element-wise kernels run on dense memory)."""
        w, _ = layers[0]
        z = torch.baddbmm(first, act.expand(w.shape[0], -1, -1), w[..., self.obs_dim :].transpose(1, 2))
        pre, inputs = [], []
        for w_i, b_i in layers[1:]:
            pre.append(z)
            x = self.act(z)
            inputs.append(x)
            z = torch.baddbmm(b_i.unsqueeze(1), x, w_i.transpose(1, 2))
        return z, inputs, pre

    # -- backward pieces ------------------------------------------------------------------
    def _q_back(
        self, g: torch.Tensor, layers: Layers, inputs: list, pre: list, weights: bool
    ) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor]:
        """From ``dL/dQ`` ``[n_q, N, 1]`` back to the first pre-activation ``[n_q, N, h]``;
        the (weight, bias) gradients of layers 2.. (when ``weights``), last layer first."""
        grads: list[tuple[torch.Tensor, torch.Tensor]] = []
        for i in range(len(layers) - 1, 0, -1):
            w_i = layers[i][0]
            x = inputs[i - 1]
            if weights:
                grads.append((torch.bmm(g.transpose(1, 2), x), g.sum(1)))
            g = torch.bmm(g, w_i)
            g = self.act_grad(g, pre[i - 1], x)
        return grads, g

    def _clone(self, loc: torch.Tensor, act: torch.Tensor, mask: torch.Tensor, w: float,
               inv_n: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The cloning term and its gradient with respect to ``loc`` (module doc)."""
        t = loc.tanh()
        det = t if self.box is None else t * self.box[1] + self.box[0]
        diff = (det - act) * mask.reshape(-1, 1).to(det.dtype)
        g_det = diff * (2.0 * w * inv_n)
        if self.box is not None:
            g_det = g_det * self.box[1]
        return w * diff.square().sum(-1).mean(), g_det * (1 - t * t)

    def _actor_back(self, g: torch.Tensor, cur: dict[str, torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """From the gradient at the actor's output (loc, raw scale) to its (weight, bias)
        gradients, last layer first."""
        a_grads: list[tuple[torch.Tensor, torch.Tensor]] = []
        inputs, pre = cur["inputs"], cur["pre"]
        for i in range(len(self.actor_layers) - 1, -1, -1):
            a_grads.append((g.t() @ inputs[i], g.sum(0)))
            if i > 0:
                g = self.act_grad(g @ self.actor_layers[i][0], pre[i - 1], inputs[i])
        return a_grads

    def grads(
        self, batch: TensorDictBase, clone_weight: float = 0.0, clone_mask: torch.Tensor | None = None,
        clone_relative: bool = False, clone_target: torch.Tensor | None = None,
    ) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
        """``clone_weight`` and ``clone_mask`` ``[N]`` (bool: the rows whose replayed action
        the actor is pulled toward): the cloning term, see the module doc. ``clone_relative``:
        the weight is multiplied by ``max(|loss_actor|, 1)`` (detached), as
        :meth:`uavlae.algos.sac.SAC._losses` does for the torchrl path. ``clone_target``
        ``[N, act]``: what it pulls toward, in place of the replayed action (teacher labels)."""
        nxt = batch.get("next")
        obs, act = batch.get("observation"), batch.get("action")
        next_obs = nxt.get("observation")
        reward = nxt.get("reward").reshape(-1)
        not_term = (~nxt.get("terminated")).reshape(-1)
        with torch.no_grad():
            return self._grads(obs, act, next_obs, reward, not_term, clone_weight, clone_mask, clone_relative,
                               clone_target)

    def _grads(
        self, obs: torch.Tensor, act: torch.Tensor, next_obs: torch.Tensor, reward: torch.Tensor, not_term: torch.Tensor,
        clone_weight: float = 0.0, clone_mask: torch.Tensor | None = None, clone_relative: bool = False,
        clone_target: torch.Tensor | None = None,
    ) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
        n_obs = obs.shape[0]
        inv_n = 1.0 / n_obs
        log_alpha = self.log_alpha
        alpha = log_alpha.exp()
        w1, _ = self.q_layers[0]
        n_q = w1.shape[0]

        # target (SACLoss._compute_target_v2): the next action is drawn first, as in SACLoss
        nxt = self._sample(next_obs)
        q_next, _, _ = self._q(self._q_first(next_obs, self.target_layers), nxt["action"], self.target_layers)
        next_value = (q_next.squeeze(-1) - alpha * nxt["log_prob"]).min(0)[0]
        target = reward + self.gamma * not_term * next_value

        # critic: every Q net on the replayed action
        first = self._q_first(obs, self.q_layers)
        q, q_in, q_pre = self._q(first, act, self.q_layers)
        diff = q.squeeze(-1) - target  # [n, N]
        if self.loss_function == "l2":
            loss_q = diff.square().sum(0).mean()
            g_q = diff * (2.0 * inv_n)
        elif self.loss_function == "l1":
            loss_q = diff.abs().sum(0).mean()
            g_q = diff.sign() * inv_n
        else:  # smooth_l1, beta 1
            ad = diff.abs()
            loss_q = torch.where(ad < 1.0, 0.5 * diff.square(), ad - 0.5).sum(0).mean()
            g_q = diff.clamp(-1.0, 1.0) * inv_n
        q_grads, g_z1 = self._q_back(g_q.unsqueeze(-1), self.q_layers, q_in, q_pre, weights=True)
        g_z1_t = g_z1.transpose(1, 2)  # [n, h, N]
        g_w1 = torch.cat([torch.bmm(g_z1_t, obs.expand(n_q, -1, -1)), torch.bmm(g_z1_t, act.expand(n_q, -1, -1))], dim=2)
        q_grads.append((g_w1, g_z1.sum(1)))

        # actor: a fresh action through the (detached) Q nets, then through the actor
        cur = self._sample(obs)
        q_new, qn_in, qn_pre = self._q(first, cur["action"], self.q_layers)
        q_new = q_new.squeeze(-1)
        q_min, idx = q_new.min(0)
        logp = cur["log_prob"]
        loss_actor = (alpha * logp - q_min).mean()
        g_qn = torch.zeros_like(q_new).scatter_(0, idx.unsqueeze(0), -inv_n)
        _, g_zn = self._q_back(g_qn.unsqueeze(-1), self.q_layers, qn_in, qn_pre, weights=False)
        g_act = torch.bmm(g_zn, w1[..., self.obs_dim :]).sum(0)  # dL/da [N, act]
        if self.box is not None:
            g_act = g_act * self.box[1]
        y, x, scale = cur["y"], cur["x"], cur["scale"]
        g_lp = alpha * inv_n  # dL/dlogp per sample
        # d logp/dx = -d/dx 2(log2 - x - softplus(-2x)) = 2 - 4 sigmoid(-2x); dy/dx = 1 - y^2
        g_x = g_act * (1 - y * y) + g_lp * (2.0 - 4.0 * torch.sigmoid(-2.0 * x))
        g_scale = (g_x * cur["eps"] - g_lp / scale) * (cur["pre_scale"] >= self.scale_lb)
        g_raw = g_scale * torch.sigmoid(cur["raw"] + self.scale_bias)
        loss_clone = torch.zeros((), dtype=obs.dtype)
        g_loc = g_x  # x = loc + eps * scale
        if clone_weight > 0 and clone_mask is not None:
            w = clone_weight * (max(abs(float(loss_actor)), 1.0) if clone_relative else 1.0)
            target_a = act if clone_target is None else clone_target
            loss_clone, g_clone = self._clone(cur["loc"], target_a, clone_mask, w, inv_n)
            g_loc = g_x + g_clone
        a_grads = self._actor_back(torch.cat([g_loc, g_raw], dim=1), cur)
        loss_alpha = (-log_alpha * (logp + self.target_entropy)).mean()
        g_alpha = -(logp + self.target_entropy).mean()

        # in self.params' order: actor (w, b) per layer, Q (w, b) per layer, log_alpha
        grads = [t for pair in reversed(a_grads) for t in pair] + [t for pair in reversed(q_grads) for t in pair]
        grads.append(g_alpha.reshape(log_alpha.shape))
        logs = {
            "loss_actor": loss_actor,
            "loss_qvalue": loss_q,
            "loss_alpha": loss_alpha,
            "alpha": alpha,
            "entropy": -logp.mean(),
            "loss_clone": loss_clone,
        }
        return logs, grads
