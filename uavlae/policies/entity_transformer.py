"""Attention over the entities of one slot: the network of the ``wang`` baseline.

After Wang et al. 2023 (BIT-MCS DRL-UCS-AoI-Threshold), reduced to our single DCU. The flat
observation (docs/model.md §6, :class:`uavlae.envs.world.ObservationLayout`) is cut back into one token
per entity, each with its own input projection and a learned type embedding:

==========  ========================================================  ==================
type        features (all from the normalised observation)             present when
==========  ========================================================  ==================
GE          position, position relative to the DCU, data left, TP      its presence flag
NFZ/RZ/BZ   corner, length, width, corner relative to the DCU          its presence flag
OU          position relative to the DCU, velocity                     seen (within PR)
DCU         every remaining column: position, velocity, energy, last   always
            slot's data, TA, LA (and the extra / ego columns if on)
==========  ========================================================  ==================

A pre-LN transformer encoder (no positional encoding) attends over the tokens with absent ones
masked out of the keys; the DCU token's output is the embedding the heads read. So the output
does not depend on the order of the tokens, and an absent entity (whatever its padded columns
hold) changes nothing, the two properties the tests check.

Adaptation: Wang et al.'s GTrXL is a gated Transformer-XL over *time* (memory of past steps, per
agent, several UAVs). Here the attention runs over *entities* within one slot, a different
design: the observation already lists every entity, and a single DCU has no other agents. The
pre-LN ordering is GTrXL's identity-map reordering; its GRU-style gates are replaced by plain
residuals, and there is no memory over time (OUs beyond PR are not remembered).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from uavlae.envs.world import ObservationLayout

TOKEN_TYPES = ("dcu", "ge", "nfz", "rz", "bz", "ou")


class EntityTokens(nn.Module):
    """Cuts a flat observation ``[..., D]`` into per-type tokens ``{type: (features, present)}``.

    The column order is :meth:`ObservationLayout.build`'s; the sizes come from the layout, and a
    layout whose size does not add up is an error (the env's observation changed).
    """

    def __init__(self, layout: ObservationLayout):
        super().__init__()
        if layout.frame != "world":
            # the tokens are cut at the world frame's column positions (absolute positions, the
            # DCU's own position to subtract); the ego frame lays its columns out otherwise
            raise ValueError(
                f"the entity tokens read the world-frame observation: set env.obs_frame=world "
                f"(got env.obs_frame={layout.frame})"
            )
        self.n_ge, self.n_ou = layout.n_ge, layout.n_ou
        self.n_zone = tuple(layout.n_zone)
        g, k = self.n_ge, self.n_ou
        base = 5 * g + sum(5 * n for n in self.n_zone) + 5 * k
        self.n_dcu = layout.flat_size - base  # with env.maps the maps follow; they are not tokens
        if self.n_dcu < 14:
            raise ValueError(
                f"the observation layout has {layout.flat_size} flat columns, {base} of them entities: the DCU part "
                f"({self.n_dcu}) is shorter than position, velocity, energy, slot data, TA and LA (14)"
            )
        self.feature_sizes = {"dcu": self.n_dcu, "ge": 6, "nfz": 6, "rz": 6, "bz": 6, "ou": 4}

    def forward(self, obs: Tensor) -> dict[str, tuple[Tensor, Tensor]]:
        g, k = self.n_ge, self.n_ou
        i = 0

        def take(n: int) -> Tensor:
            nonlocal i
            out = obs[..., i : i + n]
            i += n
            return out

        ge_xy = take(2 * g).unflatten(-1, (g, 2))
        ge_data, ge_tp, ge_present = take(g), take(g), take(g)
        zones = []
        for n in self.n_zone:
            zones.append((take(4 * n).unflatten(-1, (n, 4)), take(n)))
        ou_rel = take(2 * k).unflatten(-1, (k, 2))
        ou_vel = take(2 * k).unflatten(-1, (k, 2))
        ou_seen = take(k)
        dcu = take(self.n_dcu)
        p = dcu[..., :2].unsqueeze(-2)  # the DCU's position, normalised like every position column
        tokens = {
            "dcu": (dcu.unsqueeze(-2), torch.ones_like(dcu[..., :1], dtype=torch.bool)),
            "ge": (torch.cat([ge_xy, ge_xy - p, ge_data.unsqueeze(-1), ge_tp.unsqueeze(-1)], -1), ge_present > 0.5),
            "ou": (torch.cat([ou_rel, ou_vel], -1), ou_seen > 0.5),
        }
        for name, (rect, present) in zip(("nfz", "rz", "bz"), zones):
            tokens[name] = (torch.cat([rect, rect[..., :2] - p], -1), present > 0.5)
        return tokens


class EntityTransformer(nn.Module):
    """Tokens -> per-type projection + type embedding -> masked encoder -> DCU token's output.

    ``forward(obs)`` takes the flat observation ``[..., D]`` and returns ``[..., d_model]``;
    :meth:`encode` takes the token dict, so a test can drop tokens altogether.
    """

    def __init__(self, layout: ObservationLayout, d_model: int, n_heads: int, n_layers: int, ff: int):
        super().__init__()
        self.tokens = EntityTokens(layout)
        self.proj = nn.ModuleDict({t: nn.Linear(n, d_model) for t, n in self.tokens.feature_sizes.items()})
        self.type_embedding = nn.Embedding(len(TOKEN_TYPES), d_model)
        layer = nn.TransformerEncoderLayer(
            d_model, n_heads, dim_feedforward=ff, dropout=0.0, batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, n_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d_model)
        self.out_features = d_model

    def encode(self, tokens: Mapping[str, tuple[Tensor, Tensor]]) -> Tensor:
        feats, masks = [], []
        lead = tokens["dcu"][0].shape[:-2]
        for t in TOKEN_TYPES:  # the DCU first: its output is the embedding
            if t not in tokens:
                continue
            x, present = tokens[t]
            if x.shape[-2] == 0:
                continue
            e = self.proj[t](x) + self.type_embedding.weight[TOKEN_TYPES.index(t)]
            feats.append(e.reshape(-1, *e.shape[-2:]))
            masks.append(present.reshape(-1, present.shape[-1]))
        h = torch.cat(feats, dim=-2)
        absent = ~torch.cat(masks, dim=-1)
        h = self.encoder(h, src_key_padding_mask=absent)
        return self.norm(h[:, 0]).reshape(*lead, -1)

    def forward(self, obs: Tensor) -> Tensor:
        return self.encode(self.tokens(obs))


class EntityHead(nn.Module):
    """:class:`EntityTransformer` followed by an MLP head to ``out_features``."""

    def __init__(
        self, layout: ObservationLayout, out_features: int, *, d_model: int, n_heads: int, n_layers: int, ff: int,
        head_hidden: tuple[int, ...],
    ):
        super().__init__()
        self.body = EntityTransformer(layout, d_model, n_heads, n_layers, ff)
        layers: list[nn.Module] = []
        n = d_model
        for h in head_hidden:
            layers += [nn.Linear(n, h), nn.Tanh()]
            n = h
        layers.append(nn.Linear(n, out_features))
        self.head = nn.Sequential(*layers)

    def forward(self, obs: Tensor) -> Tensor:
        return self.head(self.body(obs))
