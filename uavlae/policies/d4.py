"""The symmetry group D4 of the square acting on the map observation, and the group-averaged CNN
of the ``theile`` baseline (after Theile et al. 2024, equivariant ensembles).

**The group.** Element ``e`` in 0..7 is ``R_e = Rot(k · 90°) · F^s`` with ``k = e % 4`` (rotations
counter-clockwise, +x east towards +y north) and ``s = e // 4``, ``F = diag(1, -1)`` the
reflection y -> -y. It acts on

- a 2-D vector (a velocity, a relative position, the action's mean) by ``v -> R_e v``;
- a map ``[..., S, S]`` (axes of :mod:`uavlae.envs.maps`: last axis east, the one before north,
  DCU on the centre corner) by ``(g M)(q) = M(R_e^{-1} q)``: the world rotated about the DCU;
- a per-axis scale ``(σx, σy)`` by the permutation ``|R_e|`` (a 90° rotation swaps the axes);
- an invariant column (a distance, the energy, a flag) not at all.

The action box [-1, 1]^2 is mapped onto itself by every ``R_e`` and the tanh of the action head
is element-wise and odd, so equivariance of the Gaussian's mean before the tanh is equivariance
of the action.

**The ensemble.** One shared network f reads ``g · o`` for each of the 8 elements; the actor's
output is ``(1/8) Σ_e R_e^{-1} f(R_e · o)`` (mean; the per-axis raw scales by ``|R_e^{-1}|``), the
critic's ``(1/8) Σ_e f(R_e · o)``. Then ``π(R_h · o) = R_h π(o)`` and ``V(R_h · o) = V(o)`` for
every h, whatever f's weights (tests/test_theile.py checks both on hand-built inputs).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from uavlae.envs.world import ObservationLayout

N_ELEMENTS = 8

# The scalar columns the network reads (the DCU's own, "ego" part of the flat observation): each
# pair of a vector column is rotated with the maps, the invariant columns are left as they are.
VECTOR_COLUMNS = ("ou_rel", "ou_vel", "velocity", "target", "target_dir", "bz_vec", "nfz_vec")
INVARIANT_COLUMNS = ("ou_seen", "energy_left", "slot_data", "extra")


def element(e: int) -> tuple[int, int]:
    """``(k, s)`` of element ``e``: ``k`` quarter turns after ``s`` reflections y -> -y."""
    if not 0 <= e < N_ELEMENTS:
        raise ValueError(f"a D4 element is 0..7, got {e}")
    return e % 4, e // 4


def matrix(e: int) -> Tensor:
    """``R_e`` as a 2 x 2 float tensor."""
    k, s = element(e)
    rot = torch.tensor([[0.0, -1.0], [1.0, 0.0]])
    m = torch.linalg.matrix_power(rot, k)
    return m @ torch.diag(torch.tensor([1.0, -1.0])) if s else m


def matrices() -> Tensor:
    """All ``R_e``, ``[8, 2, 2]``."""
    return torch.stack([matrix(e) for e in range(N_ELEMENTS)])


def transform_map(m: Tensor, e: int) -> Tensor:
    """``g_e · m`` for maps ``[..., S, S]`` (rows north, columns east, centred grid)."""
    k, s = element(e)
    if s:  # y -> -y: row i -> S-1-i
        m = torch.flip(m, dims=(-2,))
    # a quarter turn counter-clockwise: out[i, j] = m[S-1-j, i]
    return torch.rot90(m, k, dims=(-1, -2)) if k else m


class MapInputs(nn.Module):
    """Cuts the env's observation ``[N, D]`` (``env.maps.enabled``) into the local and global maps
    ``[N, C, S, S]``, the vector columns ``[N, V, 2]`` and the invariant columns ``[N, U]``."""

    def __init__(self, layout: ObservationLayout):
        super().__init__()
        if not layout.map_shapes:
            raise ValueError("the theile networks read map observations: set env.maps.enabled=true")
        cols = layout.columns()
        vec = [i for n in VECTOR_COLUMNS if n in cols for i in range(*cols[n].indices(layout.flat_size))]
        inv = [i for n in INVARIANT_COLUMNS if n in cols for i in range(*cols[n].indices(layout.flat_size))]
        self.register_buffer("vec_idx", torch.tensor(vec, dtype=torch.int64), persistent=False)
        self.register_buffer("inv_idx", torch.tensor(inv, dtype=torch.int64), persistent=False)
        self.flat_size = layout.flat_size
        self.local_shape, self.global_shape = layout.map_shapes
        self.n_vec, self.n_inv = len(vec) // 2, len(inv)

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        n_local = self.local_shape[0] * self.local_shape[1] * self.local_shape[2]
        maps = obs[..., self.flat_size :]
        local = maps[..., :n_local].unflatten(-1, self.local_shape)
        glob = maps[..., n_local:].unflatten(-1, self.global_shape)
        vec = obs[..., self.vec_idx].unflatten(-1, (self.n_vec, 2))
        return local, glob, vec, obs[..., self.inv_idx]


def _conv_stack(c_in: int, channels: tuple[int, ...], size: int, stride: int) -> tuple[nn.Sequential, int]:
    layers: list[nn.Module] = []
    for c in channels:
        layers += [nn.Conv2d(c_in, c, kernel_size=3, stride=stride, padding=1), nn.ReLU()]
        c_in = c
        size = (size - 1) // stride + 1
    layers.append(nn.Flatten())
    return nn.Sequential(*layers), c_in * size * size


class MapNet(nn.Module):
    """The shared member network f: a CNN on each map, concatenated with the scalar columns,
    then an MLP: ``(local, global, vec, inv)`` -> ``[N, out_features]``."""

    def __init__(self, inputs: MapInputs, out_features: int, channels: tuple[int, ...], stride: int,
                 hidden: tuple[int, ...]):
        super().__init__()
        self.local_cnn, n_local = _conv_stack(inputs.local_shape[0], channels, inputs.local_shape[1], stride)
        self.global_cnn, n_global = _conv_stack(inputs.global_shape[0], channels, inputs.global_shape[1], stride)
        n_in = n_local + n_global + 2 * inputs.n_vec + inputs.n_inv
        layers: list[nn.Module] = []
        for h in hidden:
            layers += [nn.Linear(n_in, h), nn.ReLU()]
            n_in = h
        layers.append(nn.Linear(n_in, out_features))
        self.head = nn.Sequential(*layers)

    def forward(self, local: Tensor, glob: Tensor, vec: Tensor, inv: Tensor) -> Tensor:
        feats = [self.local_cnn(local), self.global_cnn(glob), vec.flatten(-2), inv]
        return self.head(torch.cat(feats, dim=-1))


class D4Ensemble(nn.Module):
    """The group average of one :class:`MapNet` over D4 (module doc).

    ``kind="action"``: the output is ``[mean (act_dim = 2), raw scale (2)]`` before the scale
    mapping, each member's mean brought back by ``R_e^{-1}`` and its raw scales by ``|R_e^{-1}|``;
    ``kind="value"``: one invariant output. :meth:`members` gives the 8 back-transformed outputs
    ``[8, ..., out]``; ``forward`` their mean ``[..., out]``."""

    def __init__(self, layout: ObservationLayout, kind: str, channels: tuple[int, ...] = (8, 16), stride: int = 2,
                 hidden: tuple[int, ...] = (64, 64)):
        super().__init__()
        if kind not in ("action", "value"):
            raise ValueError(f"kind must be 'action' or 'value', got {kind!r}")
        self.kind = kind
        self.inputs = MapInputs(layout)
        self.net = MapNet(self.inputs, 4 if kind == "action" else 1, tuple(channels), stride, tuple(hidden))
        r = matrices()
        self.register_buffer("r", r, persistent=False)  # [8, 2, 2]
        self.register_buffer("r_inv", r.transpose(-1, -2).contiguous(), persistent=False)  # orthogonal
        # With keep_members, a forward pass under autograd keeps (its input, its members) until
        # members_of takes them: the regulariser on the minibatch PPO's loss has just run the actor
        # on needs no second pass of the 8 members.
        self.keep_members = False
        self._kept: tuple[Tensor, Tensor] | None = None

    def members(self, obs: Tensor) -> Tensor:
        lead = obs.shape[:-1]
        local, glob, vec, inv = self.inputs(obs.reshape(-1, obs.shape[-1]))
        n = local.shape[0]
        # the 8 transformed copies side by side in the batch: one pass of the shared network
        local_g = torch.cat([transform_map(local, e) for e in range(N_ELEMENTS)])
        glob_g = torch.cat([transform_map(glob, e) for e in range(N_ELEMENTS)])
        vec_g = torch.einsum("eij,nvj->envi", self.r, vec).reshape(N_ELEMENTS * n, *vec.shape[1:])
        inv_g = inv.repeat(N_ELEMENTS, 1)
        out = self.net(local_g, glob_g, vec_g, inv_g).unflatten(0, (N_ELEMENTS, n))  # [8, n, out]
        if self.kind == "action":
            loc = torch.einsum("eij,enj->eni", self.r_inv, out[..., :2])
            scale = torch.einsum("eij,enj->eni", self.r_inv.abs(), out[..., 2:])
            out = torch.cat([loc, scale], dim=-1)
        return out.reshape(N_ELEMENTS, *lead, out.shape[-1])

    def forward(self, obs: Tensor) -> Tensor:
        members = self.members(obs)
        if self.keep_members and torch.is_grad_enabled():
            self._kept = (obs, members)
        return members.mean(0)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_kept"] = None  # a pass's autograd graph is no part of the module (copies, pickles)
        return state

    def members_of(self, obs: Tensor) -> Tensor:
        """:meth:`members` of ``obs``: those the last forward pass kept when it ran on this very
        tensor, else a new pass. Either way nothing stays kept."""
        kept, self._kept = self._kept, None
        if kept is not None and kept[0] is obs:
            return kept[1]
        return self.members(obs)


def member_spread(members: Tensor) -> Tensor:
    """The regulariser: the mean over the batch of (1/8) Σ_e ||m_e − m̄||², ``members``
    ``[8, ..., d]`` (0 when every member agrees)."""
    return (members - members.mean(0, keepdim=True)).pow(2).sum(-1).mean()
