"""draw_scenario writes a plausible PNG from a Scenario, a scenario TensorDict or an env state."""

import torch
from matplotlib.figure import Figure
from matplotlib.image import imread

from uavlae.envs.config import EnvConfig
from uavlae.envs.render import draw_scenario, figure_to_rgb
from uavlae.envs.scenario import Scenario, stack_scenarios
from uavlae.envs.uav_env import UAVEnv

CFG = EnvConfig()
SC = Scenario(
    nfz=[(100.0, 100.0, 160.0, 160.0)], rz=[(300.0, 300.0, 360.0, 380.0)], bz=[(200.0, 50.0, 260.0, 120.0)],
    ge_pos=[(50.0, 400.0), (420.0, 420.0)], ge_data=[1.5, 2.0], ou_pos=[(250.0, 250.0)], ou_vel=[(3.0, 1.0)],
    start=(12.5, 487.5),
)


def _check_png(path):
    assert path.exists()
    raw = path.read_bytes()
    assert raw[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(raw) > 10_000
    img = imread(path)
    h, w = img.shape[:2]
    assert 400 <= h <= 3000 and 400 <= w <= 4000


def test_scenario_png(tmp_path):
    traj = torch.tensor([[12.5, 487.5], [100.0, 400.0], [480.0, 10.0]])
    fig = draw_scenario(SC, traj, path=tmp_path / "sub" / "scenario.png", title="hand-made", cfg=CFG)
    assert isinstance(fig, Figure)
    _check_png(tmp_path / "sub" / "scenario.png")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    for want in ("no-fly zone", "residential zone", "building", "trajectory", "landing area"):
        assert want in labels


def test_env_state_with_several_trajectories(tmp_path):
    env = UAVEnv(CFG, batch_size=[3], seed=0)
    td = env.reset()
    trajs = [torch.cumsum(torch.randn(20, 2) * 5, 0) + 250 for _ in range(3)]
    fig = draw_scenario(td, trajs, path=tmp_path / "state.png", index=2, labels=["a", "b", "c"])
    _check_png(tmp_path / "state.png")
    assert len(fig.axes[0].lines) >= 9  # one line + start + end marker per trajectory
    # one row of the "state" entries and a batched scenario TensorDict work too
    draw_scenario(td["state"][1], path=tmp_path / "row.png")
    _check_png(tmp_path / "row.png")
    rgb = figure_to_rgb(draw_scenario(stack_scenarios([SC, SC], CFG), index=1))
    assert rgb.dtype.name == "uint8" and rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.std() > 0
