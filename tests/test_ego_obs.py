"""The observation in the DCU's own frame (``env.obs_frame: ego``, docs/model.md §6): every column
of a hand-placed scenario by hand, independence of the entities' indices, the env's specs, the maps
and the learners that read the layout."""

import gymnasium
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from uavlae.envs import UAVEnv
from uavlae.envs.config import make_env_config
from uavlae.envs.gym_adapter import GYM_ID
from uavlae.envs.world import ObservationLayout, nearest_distances
from uavlae.experiments.report import world_label
from uavlae.policies.d4 import MapInputs
from uavlae.policies.entity_transformer import EntityTokens

# A 300 x 400 m area, so that the diagonal is 500 m and every expected number is a short decimal;
# TA and LA moved into its corners. Padded to 3 GEs, 2 OUs and 2 zones of each kind.
HAND = {
    "area": {"x_size": 300.0, "y_size": 400.0, "takeoff": [0.0, 375.0, 25.0, 400.0],
             "landing": [270.0, 0.0, 300.0, 25.0]},
    "ge": {"count": {"min": 1, "max": 3}},
    "ou": {"count": {"min": 1, "max": 2}},
    "zones": {"n_nfz": {"min": 1, "max": 2}, "n_rz": {"min": 1, "max": 2}, "n_bz": {"min": 1, "max": 2}},
    "obs_frame": "ego",
    "ego_features": True,
}


def _hand_state(cfg) -> dict[str, torch.Tensor]:
    """DCU at (120, 200) flying (3, -4) m/s. GE0 emptied 50 m away, GE1 absent (garbage in its
    padding), GE2 with 2.4 of data 100 m north. NFZ0 absent, NFZ1 north-east; RZ0 south-east, RZ1
    around the DCU; BZ0 south-west, BZ1 absent. OU0 50 m away (unseen), OU1 15 m away (seen)."""

    def f(x):
        return torch.tensor([x], dtype=torch.float32)

    def b(x):
        return torch.tensor([x], dtype=torch.bool)

    s = {
        "position": f([120.0, 200.0]), "velocity": f([3.0, -4.0]), "energy_left": f(6e5),
        "slot_data": f(1.5), "step": torch.tensor([250]),
        "ge_pos": f([[150.0, 160.0], [7.0, 9.0], [120.0, 300.0]]), "ge_remaining": f([0.0, 1.0, 2.4]),
        "ge_mask": b([True, False, True]),
        "nfz": f([[1.0, 2.0, 3.0, 4.0], [150.0, 240.0, 210.0, 300.0]]), "nfz_mask": b([False, True]),
        "rz": f([[180.0, 40.0, 240.0, 120.0], [90.0, 180.0, 150.0, 260.0]]), "rz_mask": b([True, True]),
        "bz": f([[60.0, 140.0, 90.0, 180.0], [5.0, 5.0, 6.0, 6.0]]), "bz_mask": b([True, False]),
        "takeoff": f(list(cfg.area.takeoff)), "landing": f(list(cfg.area.landing)),
        "ou_pos": f([[150.0, 240.0], [132.0, 209.0]]), "ou_vel": f([[5.0, 5.0], [2.0, -1.0]]),
        "ou_mask": b([True, True]),
    }
    s.update(nearest_distances(s, cfg))
    return s


# (column name, expected values), in the layout's order; X = 300, Y = 400, diagonal 500,
# obs_distance_scale 50, data_max 3, v_max 10, PR 20, E_limit 8e5, t_max 1000
HAND_EXPECTED = [
    # GE2 has data: (120-120, 300-200) / 500; GE0 emptied: (150-120, 160-200) / 500; GE1 absent
    ("ge_rel", [0.0, 0.2, 0.06, -0.08, 0.0, 0.0]),
    ("ge_data", [0.8, 0.0, 0.0]),  # 2.4 / 3, GE0 empty, GE1 absent (its 1.0 of padding dropped)
    ("ge_has_data", [1.0, 0.0, 0.0]),
    ("ge_present", [1.0, 1.0, 0.0]),
    # NFZ1: (150-120, 240-200, 210-120, 300-200) / (300, 400, 300, 400); NFZ0 absent
    ("nfz_rel", [0.1, 0.1, 0.3, 0.25, 0.0, 0.0, 0.0, 0.0]),
    ("nfz_near", [0.6, 0.8, 0.0, 0.0]),  # nearest point (150, 240): (30, 40), 50 m = the scale: / 50
    ("nfz_inside", [0.0, 0.0]),
    ("nfz_present", [1.0, 0.0]),
    # RZ1 first (the DCU is inside): (90-120, 180-200, 150-120, 260-200) = (-30, -20, 30, 60);
    # RZ0: (180-120, 40-200, 240-120, 120-200) = (60, -160, 120, -80); / (300, 400, 300, 400)
    ("rz_rel", [-0.1, -0.05, 0.1, 0.15, 0.2, -0.4, 0.4, -0.2]),
    # inside RZ1: 0; RZ0's nearest point (180, 120): (60, -80), 100 m saturated to 50: (30, -40) / 50
    ("rz_near", [0.0, 0.0, 0.6, -0.8]),
    ("rz_inside", [1.0, 0.0]),
    ("rz_present", [1.0, 1.0]),
    # BZ0: (60-120, 140-200, 90-120, 180-200) = (-60, -60, -30, -20) / (300, 400, 300, 400); BZ1 absent
    ("bz_rel", [-0.2, -0.15, -0.1, -0.05, 0.0, 0.0, 0.0, 0.0]),
    ("bz_near", [-0.6, -0.4, 0.0, 0.0]),  # nearest point (90, 180): (-30, -20), 36.06 m < 50: / 50
    ("bz_inside", [0.0, 0.0]),
    ("bz_present", [1.0, 0.0]),
    ("boundary", [0.4, 0.6, 0.5, 0.5]),  # 120 / 300, (300-120) / 300, 200 / 400, (400-200) / 400
    # LA (270-120, 0-200, 300-120, 25-200) = (150, -200, 180, -175) / (300, 400, 300, 400)
    ("landing_rel", [0.5, -0.5, 0.6, -0.4375]),
    ("landing_near", [0.3, -0.35]),  # nearest point (270, 25): (150, -175) / 500
    ("in_landing", [0.0]),
    ("ou_rel", [0.6, 0.45, 0.0, 0.0]),  # OU1 (132-120, 209-200) = (12, 9), 15 m <= 20: / 20; OU0 unseen
    ("ou_vel", [0.2, -0.1, 0.0, 0.0]),  # OU1's (2, -1) / 10
    ("ou_seen", [1.0, 0.0]),
    ("energy_left", [0.75]),  # 6e5 / 8e5
    ("velocity", [0.3, -0.4]),  # (3, -4) / 10
    ("slot_data", [0.5]),  # 1.5 / 3
    ("slots_left", [0.75]),  # 1 - 250 / 1000
    ("goal_dir", [0.0, 1.0]),  # to GE2, the nearest with data: (0, 100) / 100
    ("goal_dist", [0.2]),  # 100 / 500
    # d_bz = |(-30, -20)| = 36.0555 / 50; d_nfz 50 / 50; d_rz 0 (inside RZ1); d_boundary 120
    # saturated at 50: 1; d_la = |(150, -175)| = 230.4886 / 500; in an RZ
    ("extra", [0.7211103, 1.0, 0.0, 1.0, 0.4609772, 1.0]),
    ("target", [0.0, 0.2]),  # ego_features: (0, 100) / 500, its direction, then BZ and NFZ as above
    ("target_dir", [0.0, 1.0]),
    ("bz_vec", [-0.6, -0.4]),
    ("nfz_vec", [0.6, 0.8]),
]


def test_every_ego_column_of_a_hand_placed_scenario():
    cfg = make_env_config(HAND)
    layout = ObservationLayout(cfg)
    cols = layout.columns()
    assert list(cols) == [name for name, _ in HAND_EXPECTED]
    assert {n: sl.stop - sl.start for n, sl in cols.items()} == {n: len(v) for n, v in HAND_EXPECTED}
    # 5·3 GE + 3·8·2 zone + 4 boundary + 7 LA + 5·2 OU + 5 DCU + 3 target + 6 extra + 8 ego = 106
    assert layout.flat_size == layout.size == 106
    obs = layout.build(_hand_state(cfg))
    assert obs.shape == (1, 106)
    for name, expected in HAND_EXPECTED:
        torch.testing.assert_close(obs[0, cols[name]], torch.tensor(expected), msg=name)


def test_column_counts_at_the_defaults():
    # 5·15 GE + 3·8·3 zone + 4 + 7 + 5·7 OU + 5 + 3 = 201, + 6 extra (on by default) = 207
    assert ObservationLayout(make_env_config({"obs_frame": "ego"})).size == 207
    assert ObservationLayout(make_env_config({"obs_frame": "ego", "extra_features": False})).size == 201
    assert ObservationLayout(make_env_config({"obs_frame": "ego", "ego_features": True})).size == 215
    assert ObservationLayout(make_env_config({})).size == 175  # the world frame, unchanged


def test_bad_frame_names_the_key():
    with pytest.raises(ValueError, match="obs_frame"):
        make_env_config({"obs_frame": "heading"})


def test_reports_name_the_ego_frame_as_a_learning_aid():
    assert world_label({"obs_frame": "world"}) == world_label({}) == "SPEC world"
    assert world_label({"obs_frame": "ego", "ego_features": True}) == "learning-aid world: ego features, ego frame"


def _permute(s: dict[str, torch.Tensor], keys: tuple[str, ...], perm: torch.Tensor) -> None:
    for k in keys:
        s[k] = s[k][:, perm]


def test_permuting_entity_indices_leaves_the_ego_observation_unchanged():
    env = UAVEnv({"obs_frame": "ego", "ego_features": True}, batch_size=[8], seed=4)
    torch.manual_seed(0)
    td = env.rollout(6, break_when_any_done=False)
    s = {k: v[:, -1].clone() for k, v in td["next", "state"].items()}
    s["ge_remaining"][:, ::3] = 0.0  # some GEs emptied, so that both groups are sorted
    # row 0 inside two overlapping RZs: a tie at distance 0, broken by the distance to the centre
    p = s["position"][0]
    s["rz"][0, :2] = torch.stack([torch.cat([p - 10, p + 30]), torch.cat([p - 40, p + 5])])
    s["rz_mask"][0, :2] = True
    s.update(nearest_distances(s, env.cfg))
    obs = env.layout.build(s)
    gen = torch.Generator().manual_seed(1)
    for _ in range(3):
        t = dict(s)
        _permute(t, ("ge_pos", "ge_mask", "ge_remaining"), torch.randperm(s["ge_mask"].shape[1], generator=gen))
        for name in ("nfz", "rz", "bz"):
            _permute(t, (name, name + "_mask"), torch.randperm(s[name + "_mask"].shape[1], generator=gen))
        _permute(t, ("ou_pos", "ou_vel", "ou_mask"), torch.randperm(s["ou_mask"].shape[1], generator=gen))
        assert torch.equal(env.layout.build(t), obs)
    # the world frame does depend on the order, so the permutations above did move entities
    world = ObservationLayout(make_env_config({}))
    assert not torch.equal(world.build(t), world.build(s))


@pytest.mark.parametrize("b", [1, 16])
def test_check_env_specs_in_the_ego_frame(b):
    env = UAVEnv({"obs_frame": "ego"}, batch_size=[b], seed=0)
    check_env_specs(env, seed=0)
    td = env.rollout(4, break_when_any_done=False)
    assert td["next", "observation"].shape == (b, 4, 207)
    assert torch.isfinite(td["next", "observation"]).all()


def test_any_leading_batch_shape():
    env = UAVEnv({"obs_frame": "ego"}, batch_size=[3], seed=2)
    td = env.rollout(4, break_when_any_done=False)
    states = dict(td["next", "state"].items())
    flat = env.layout.build({k: v.flatten(0, 1) for k, v in states.items()})
    torch.testing.assert_close(env.layout.build(states), flat.unflatten(0, (3, 4)), rtol=0, atol=0)
    torch.testing.assert_close(td["next", "observation"], flat.unflatten(0, (3, 4)), rtol=0, atol=0)


TINY_MAPS = {"enabled": True, "local_size": 4, "global_size": 4}


def test_maps_compose_with_the_ego_frame_and_theile_reads_the_same_inputs():
    ego = UAVEnv({"obs_frame": "ego", "maps": TINY_MAPS}, batch_size=[2], seed=3)
    world = UAVEnv({"maps": TINY_MAPS}, batch_size=[2], seed=3)
    td = ego.reset()
    s = dict(td["state"].items())
    flat_only = ObservationLayout(make_env_config({"obs_frame": "ego"}))
    assert ego.layout.size == 207 + 2 * 7 * 16 and td["observation"].shape == (2, ego.layout.size)
    assert torch.equal(td["observation"][:, :207], flat_only.build(s))
    # theile's networks read the maps and the columns it names (OUs, velocity, energy, last slot's
    # data, extra), which mean the same in both frames: it works unchanged
    a, w = MapInputs(ego.layout)(td["observation"]), MapInputs(world.layout)(world.layout.build(s))
    for x, y in zip(a, w):
        assert torch.equal(x, y)


def test_entity_tokens_refuse_the_ego_frame():
    with pytest.raises(ValueError, match="env.obs_frame"):
        EntityTokens(ObservationLayout(make_env_config({"obs_frame": "ego"})))


def test_gym_adapter_in_the_ego_frame():
    env = gymnasium.make(GYM_ID, cfg=make_env_config({"obs_frame": "ego"}))
    obs, _ = env.reset(seed=0)
    assert env.observation_space.shape == obs.shape == (207,)
