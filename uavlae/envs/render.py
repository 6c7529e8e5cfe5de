"""Top-down picture of one scenario or one env state, with optional trajectories.

Uses matplotlib's object API on an Agg canvas (no pyplot, no window, no global figure list):
safe in tests, workers and headless machines.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from tensordict import TensorDictBase

from uavlae.envs.config import EnvConfig, make_env_config

ZONE_STYLE = {  # name: (face colour, edge colour, legend label)
    "nfz": ("#e74c3c", "#a93226", "no-fly zone"),
    "rz": ("#f4d03f", "#b7950b", "residential zone"),
    "bz": ("#95a5a6", "#4d5656", "building"),
}
TA_COLOUR, LA_COLOUR = "#5dade2", "#58d68d"
GE_COLOUR, OU_COLOUR = "#1f618d", "#8e44ad"
OU_ARROW_SECONDS = 3.0  # an OU's arrow shows where it is this many seconds later


def _np(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _scene(obj: Any, cfg: EnvConfig, index: int) -> dict[str, np.ndarray]:
    """Plain numpy arrays of one scene from a Scenario, a scenario/state TensorDict or a dict."""
    if not isinstance(obj, (TensorDictBase, Mapping)):
        from uavlae.envs.scenario import stack_scenarios  # a Scenario dataclass

        obj = stack_scenarios([obj], cfg)
    if isinstance(obj, TensorDictBase):
        if "state" in obj.keys():
            obj = obj.get("state")
        if obj.batch_dims:
            obj = obj.reshape(-1)[index]
        src = {k: obj.get(k) for k in obj.keys()}
    else:
        state = obj.get("state")
        src = dict(state if isinstance(state, (Mapping, TensorDictBase)) else obj)
    out = {k: _np(v) for k, v in src.items() if not isinstance(v, (TensorDictBase, Mapping))}
    # a batched dict (leading batch dim on positions) becomes one row
    if "ge_pos" in out and out["ge_pos"].ndim == 3:
        out = {k: (v[index] if v.ndim >= 1 else v) for k, v in out.items()}
    return out


def _rects(scene: Mapping[str, np.ndarray], name: str) -> np.ndarray:
    r = scene.get(name)
    if r is None:
        return np.zeros((0, 4))
    r = np.asarray(r, dtype=float).reshape(-1, 4)
    m = scene.get(name + "_mask")
    return r[np.asarray(m, dtype=bool).reshape(-1)] if m is not None else r


def _as_trajectories(trajectories: Any) -> list[np.ndarray]:
    if trajectories is None:
        return []
    if isinstance(trajectories, (torch.Tensor, np.ndarray)):
        t = _np(trajectories)
        return [t] if t.ndim == 2 else [t[:, i] for i in range(t.shape[1])]  # [T,2] or [T,B,2]
    return [_np(t).reshape(-1, 2) for t in trajectories]


def draw_scenario(
    scenario_or_state: Any,
    trajectories: Any = None,
    path: str | Path | None = None,
    title: str | None = None,
    cfg: EnvConfig | Mapping | None = None,
    *,
    index: int = 0,
    labels: Sequence[str] | None = None,
    ge_left: Any = None,
    figsize: tuple[float, float] = (7.0, 7.0),
    dpi: int = 110,
) -> Figure:
    """Draw the area, TA/LA, zones, GEs, OUs and trajectories; save a PNG when ``path`` is set.

    Args:
        scenario_or_state: a ``Scenario``; a scenario TensorDict (docs/env_contract.md); an env
            tensordict (its ``("state", ...)`` entries are used) or its ``"state"`` sub-tensordict;
            or a plain dict of the same keys. Batched inputs are drawn at row ``index``.
        trajectories: one ``[T, 2]`` array, a ``[T, N, 2]`` array, or a list of ``[T_i, 2]``.
        path: where to write the PNG (parent folders are created).
        title: the axes title.
        cfg: the env config (area size, TA, LA, data range); default docs/model.md's.
        labels: one legend label per trajectory.
        ge_left: the data each GE holds at the end of the trajectory (``[G]``, the scene's GE
            order): the GEs are drawn so, an emptied one hollow, not at the scene's own data.
    """
    cfg = make_env_config(cfg)
    a = cfg.area
    scene = _scene(scenario_or_state, cfg, index)
    if ge_left is not None:
        scene["ge_remaining"] = _np(ge_left).reshape(-1)
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_xlim(-0.02 * a.x_size, 1.02 * a.x_size)
    ax.set_ylim(-0.02 * a.y_size, 1.02 * a.y_size)
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.add_patch(Rectangle((0, 0), a.x_size, a.y_size, fill=False, edgecolor="black", lw=1.2))
    handles = _draw_zones(ax, scene, cfg) + _draw_ges(ax, scene, cfg) + _draw_ous(ax, scene) + _draw_dcu(ax, scene)
    handles += _draw_trajectories(ax, _as_trajectories(trajectories), labels)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, format="png", bbox_inches="tight")
    return fig


def _rect(ax: Any, r: Sequence[float], face: str, edge: str, alpha: float, z: int) -> None:
    ax.add_patch(Rectangle((r[0], r[1]), r[2] - r[0], r[3] - r[1], facecolor=face, edgecolor=edge,
                           alpha=alpha, lw=1.0, zorder=z))


def _draw_zones(ax: Any, scene: Mapping[str, Any], cfg: EnvConfig) -> list[Any]:
    """TA, LA and the zones (RZ under NFZ under BZ)."""
    a = cfg.area
    ta = _np(scene["takeoff"]).reshape(4) if "takeoff" in scene else np.asarray(a.takeoff)
    la = _np(scene["landing"]).reshape(4) if "landing" in scene else np.asarray(a.landing)
    _rect(ax, ta, TA_COLOUR, TA_COLOUR, 0.5, 1)
    _rect(ax, la, LA_COLOUR, LA_COLOUR, 0.5, 1)
    handles: list[Any] = [Patch(color=TA_COLOUR, alpha=0.5, label="take-off area"),
                          Patch(color=LA_COLOUR, alpha=0.5, label="landing area")]
    for name in ("rz", "nfz", "bz"):
        face, edge, label = ZONE_STYLE[name]
        rs = _rects(scene, name)
        for r in rs:
            _rect(ax, r, face, edge, 0.35 if name == "rz" else 0.6, 2 if name == "rz" else 3)
        if len(rs):
            handles.append(Patch(facecolor=face, edgecolor=edge, alpha=0.6, label=label))
    return handles


def _draw_ges(ax: Any, scene: Mapping[str, Any], cfg: EnvConfig) -> list[Any]:
    """GEs: marker area grows with the data still to collect; collected ones are hollow."""
    if "ge_pos" not in scene:
        return []
    handles: list[Any] = []
    pos = np.asarray(scene["ge_pos"], dtype=float).reshape(-1, 2)
    mask = np.asarray(scene.get("ge_mask", np.ones(len(pos), bool)), dtype=bool).reshape(-1)
    rem = scene.get("ge_remaining", scene.get("ge_data"))
    rem = np.zeros(len(pos)) if rem is None else np.asarray(rem, dtype=float).reshape(-1)
    pos, rem = pos[mask], rem[mask]
    size = 15.0 + 70.0 * np.clip(rem / cfg.ge.data_max, 0.0, 1.0)
    full = rem > 0
    if full.any():
        ax.scatter(pos[full, 0], pos[full, 1], s=size[full], color=GE_COLOUR, zorder=5)
        handles.append(Line2D([], [], ls="", marker="o", color=GE_COLOUR, label="GE (size: data left)"))
    if (~full).any():
        ax.scatter(pos[~full, 0], pos[~full, 1], s=size[~full], facecolors="none", edgecolors=GE_COLOUR, zorder=5)
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", color=GE_COLOUR, label="GE collected"))
    return handles


def _draw_ous(ax: Any, scene: Mapping[str, Any]) -> list[Any]:
    """Other UAVs with their velocity."""
    if "ou_pos" not in scene:
        return []
    pos = np.asarray(scene["ou_pos"], dtype=float).reshape(-1, 2)
    mask = np.asarray(scene.get("ou_mask", np.ones(len(pos), bool)), dtype=bool).reshape(-1)
    vel = np.asarray(scene.get("ou_vel", np.zeros_like(pos)), dtype=float).reshape(-1, 2)
    pos, vel = pos[mask], vel[mask]
    if not len(pos):
        return []
    ax.scatter(pos[:, 0], pos[:, 1], marker="^", s=40, color=OU_COLOUR, zorder=6)
    ax.quiver(pos[:, 0], pos[:, 1], vel[:, 0] * OU_ARROW_SECONDS, vel[:, 1] * OU_ARROW_SECONDS,
              angles="xy", scale_units="xy", scale=1.0, color=OU_COLOUR, width=0.004, zorder=6)
    return [Line2D([], [], ls="", marker="^", color=OU_COLOUR, label=f"other UAV (arrow: {OU_ARROW_SECONDS:g} s)")]


def _draw_dcu(ax: Any, scene: Mapping[str, Any]) -> list[Any]:
    """The DCU: its start (a scenario) or its current position (a state)."""
    dcu = scene.get("position", scene.get("start"))
    if dcu is None:
        return []
    d = np.asarray(dcu, dtype=float).reshape(2)
    ax.scatter([d[0]], [d[1]], marker="*", s=140, color="black", zorder=8)
    return [Line2D([], [], ls="", marker="*", ms=10, color="black", label="DCU" if "position" in scene else "start")]


def _draw_trajectories(ax: Any, trajs: list[np.ndarray], labels: Sequence[str] | None) -> list[Any]:
    handles: list[Any] = []
    cmap = matplotlib.colormaps["tab10"]
    for i, t in enumerate(trajs):
        if len(t) == 0:
            continue
        label = labels[i] if labels is not None and i < len(labels) else ("trajectory" if len(trajs) == 1 else f"trajectory {i}")
        (line,) = ax.plot(t[:, 0], t[:, 1], "-", lw=1.6, color=cmap(i % 10), zorder=7, label=label)
        colour = line.get_color()
        ax.plot(t[0, 0], t[0, 1], "o", ms=6, color=colour, zorder=9)
        ax.plot(t[-1, 0], t[-1, 1], "s", ms=6, mfc="white", mec=colour, mew=1.8, zorder=9)
        handles.append(line)
    if trajs:
        handles += [Line2D([], [], ls="", marker="o", color="grey", label="trajectory start"),
                    Line2D([], [], ls="", marker="s", mfc="white", mec="grey", label="trajectory end")]
    return handles


# how an episode ended, from its record (uavlae.envs.metrics): the first that holds, in this order
_ENDINGS = (("bz_collision", "crashed into a building"), ("nfz_entry", "entered a no-fly zone"),
            ("ou_collision", "collided with another UAV"), ("landed", "landed"),
            ("energy_exhausted", "ran out of energy"), ("truncated", "out of time"))


def episode_outcome(record: Mapping[str, Any]) -> str:
    """One episode's outcome for a picture's title, from its record (a row of ``episodes.csv``):
    how it ended, the share of the data it collected, and a speeding or boundary exit on the way,
    e.g. ``"landed, DCR 0.83, sped in an RZ"``."""
    flag = {k: bool(_np(v)) for k, v in record.items() if k in dict(_ENDINGS) or k in ("rz_speeding", "boundary_exit")}
    how = next((text for key, text in _ENDINGS if flag.get(key)), "ended")
    total = float(_np(record.get("data_total", 0.0)))
    out = how + (f", DCR {float(_np(record['data_collected'])) / total:.2f}" if total > 0 else "")
    if flag.get("boundary_exit"):
        out += ", left the area"
    if flag.get("rz_speeding"):
        out += ", sped in an RZ"
    return out


def figure_to_rgb(fig: Figure) -> np.ndarray:
    """An ``[H, W, 3]`` uint8 image of a figure drawn on an Agg canvas."""
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
