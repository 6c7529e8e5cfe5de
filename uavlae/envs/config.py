"""Validated physical parameters of the world (docs/model.md §1-§7).

Every number of the model lives here with its SPEC default; the Hydra group ``conf/env/``
mirrors this model one-to-one. Validation is strict: unknown keys, NaN, negative sizes,
min > max and counts above their padding maximum raise a ``ValueError`` naming the field.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from uavlae.validation import StrictModel, parse_model

Rect = tuple[float, float, float, float]  # (x0, y0, x1, y1): south-west and north-east corners


class AreaConfig(StrictModel):
    x_size: float = Field(500.0, gt=0)
    y_size: float = Field(500.0, gt=0)
    altitude: float = Field(10.0, ge=0)  # [decision] H, unstated in the paper
    takeoff: Rect = (0.0, 475.0, 25.0, 500.0)  # TA, north-west corner
    landing: Rect = (475.0, 0.0, 500.0, 25.0)  # LA, south-east corner
    start: tuple[float, float] | None = None  # [decision] None: centre of TA

    @field_validator("takeoff", "landing")
    @classmethod
    def _rect_ordered(cls, r: Rect) -> Rect:
        if not (r[2] > r[0] and r[3] > r[1]):
            raise ValueError(f"rectangle {r} must be (x0, y0, x1, y1) with x1 > x0 and y1 > y0")
        return r

    @model_validator(mode="after")
    def _inside(self) -> "AreaConfig":
        for name in ("takeoff", "landing"):
            r = getattr(self, name)
            if r[0] < 0 or r[1] < 0 or r[2] > self.x_size or r[3] > self.y_size:
                raise ValueError(f"area.{name} {r} must lie inside [0, {self.x_size}] x [0, {self.y_size}]")
        if self.start is not None:
            x, y = self.start
            if not (0 <= x <= self.x_size and 0 <= y <= self.y_size):
                raise ValueError(f"area.start {self.start} must lie inside the area")
        return self

    @property
    def start_xy(self) -> tuple[float, float]:
        if self.start is not None:
            return self.start
        t = self.takeoff
        return ((t[0] + t[2]) / 2, (t[1] + t[3]) / 2)

    @property
    def diagonal(self) -> float:
        return math.hypot(self.x_size, self.y_size)


class CountRange(StrictModel):
    """An entity count drawn uniformly in {min..max}, padded to ``pad`` (default: max)."""

    min: int = Field(ge=0)
    max: int = Field(ge=0)
    pad: int | None = Field(None, ge=0)

    @model_validator(mode="after")
    def _order(self) -> "CountRange":
        if self.min > self.max:
            raise ValueError(f"count min={self.min} must be <= max={self.max}")
        if self.pad is not None and self.max > self.pad:
            raise ValueError(f"count max={self.max} exceeds its padding maximum pad={self.pad}")
        return self

    @property
    def padded(self) -> int:
        return self.pad if self.pad is not None else self.max


class ZonesConfig(StrictModel):
    side_min: float = Field(50.0, gt=0)
    side_max: float = Field(200.0, gt=0)
    n_nfz: CountRange = CountRange(min=1, max=3)
    n_rz: CountRange = CountRange(min=1, max=3)
    n_bz: CountRange = CountRange(min=1, max=3)

    @model_validator(mode="after")
    def _order(self) -> "ZonesConfig":
        if self.side_min > self.side_max:
            raise ValueError(f"zones.side_min={self.side_min} must be <= zones.side_max={self.side_max}")
        return self


class GEConfig(StrictModel):
    count: CountRange = CountRange(min=11, max=15)
    data_min: float = Field(1.0, gt=0)  # DV, Table 3
    data_max: float = Field(3.0, gt=0)
    tx_power: float = Field(0.01, gt=0)  # TP [W]

    @model_validator(mode="after")
    def _order(self) -> "GEConfig":
        if self.data_min > self.data_max:
            raise ValueError(f"ge.data_min={self.data_min} must be <= ge.data_max={self.data_max}")
        return self


class OUConfig(StrictModel):
    count: CountRange = CountRange(min=3, max=7)
    p_turn: float = Field(0.05, ge=0, le=1)  # [decision] per-slot chance of a new speed and heading
    heading_tries: int = Field(4, ge=1, le=64)  # redraws before an OU hovers instead


class MotionConfig(StrictModel):
    t_fly: float = Field(1.0, gt=0)
    t_hover: float = Field(1.0, ge=0)
    v_max: float = Field(10.0, gt=0)
    v_limit: float = Field(5.0, gt=0)  # RZ speed limit (a rule, not physics)
    v_land: float = Field(1.0, ge=0)  # [decision] landing speed inside LA

    @model_validator(mode="after")
    def _order(self) -> "MotionConfig":
        if self.v_limit >= self.v_max:
            raise ValueError(f"motion.v_limit={self.v_limit} must be < motion.v_max={self.v_max}")
        return self


class ChannelConfig(StrictModel):
    alpha: float = Field(0.36, gt=0)  # [decision] gain at 1 m
    noise: float = Field(1e-6, gt=0)
    snr_threshold: float = Field(3.6, ge=0)  # tau


class EnergyConfig(StrictModel):
    """Rotary-wing propulsion model, Zeng, Xu, Zhang 2019."""

    delta: float = Field(0.012, gt=0)
    rho: float = Field(1.225, gt=0)
    s: float = Field(0.05, gt=0)
    rotor_area: float = Field(0.503, gt=0)
    omega: float = Field(300.0, gt=0)
    radius: float = Field(0.4, gt=0)
    k: float = Field(0.1, ge=0)
    weight: float = Field(20.0, gt=0)
    u_tip: float = Field(120.0, gt=0)
    v0: float = Field(4.03, gt=0)
    d0: float = Field(0.6, ge=0)
    e_total: float = Field(1e6, gt=0)  # battery [J]
    e_limit: float = Field(8e5, gt=0)  # most a mission may use (Eq. 9j)

    @model_validator(mode="after")
    def _order(self) -> "EnergyConfig":
        if self.e_limit > self.e_total:
            raise ValueError(f"energy.e_limit={self.e_limit} must be <= energy.e_total={self.e_total}")
        return self

    @property
    def p0(self) -> float:
        return self.delta / 8 * self.rho * self.s * self.rotor_area * self.omega**3 * self.radius**3

    @property
    def pi(self) -> float:
        return (1 + self.k) * self.weight**1.5 / math.sqrt(2 * self.rho * self.rotor_area)


class SafetyConfig(StrictModel):
    d_min: float = Field(5.0, ge=0)
    d_safe: float = Field(15.0, gt=0)
    r_coll: float = Field(1.0, ge=0)  # [decision] OU collision radius
    perception_radius: float = Field(20.0, gt=0)

    @model_validator(mode="after")
    def _order(self) -> "SafetyConfig":
        if self.d_min >= self.d_safe:
            raise ValueError(f"safety.d_min={self.d_min} must be < safety.d_safe={self.d_safe}")
        return self


class RewardConfig(StrictModel):
    sigma: tuple[float, float, float, float, float, float, float, float, float] = (
        8.0, 0.4, 0.4, 0.4, 0.6, 0.4, 0.6, 1.0, 0.01,
    )
    r7_variant: Literal["corrected", "as_printed"] = "corrected"  # [decision]
    d_tar: float = Field(707.0, gt=0)
    landing_bonus: float = Field(10.0, ge=0)  # [decision] beyond the paper
    crash_penalty: float = Field(10.0, ge=0)  # [decision] beyond the paper
    # [decision] beyond the paper, off by default: a progress reward w·(Φ(s') − Φ(s)) with
    # Φ = −(distance to the current target + d_tar · GEs with data left) / d_tar; the target is
    # the nearest GE with data, then LA. Its sum over an episode is Φ(end) − Φ(start), so no
    # loop or hover can farm it; w is about the reward of finishing one GE.
    progress_weight: float = Field(0.0, ge=0)
    # distance to the target: straight line, or around BZs and NFZs on a grid of this cell size
    # (uavlae.envs.geodesic; the fields are computed once per episode start)
    progress_metric: Literal["euclidean", "geodesic"] = "euclidean"
    progress_grid_cell: float = Field(10.0, gt=0, le=50.0)
    # the geodesic way keeps this far from BZs and NFZs (cells whose centre is closer are
    # blocked, except the cells of the targets themselves)
    progress_clearance: float = Field(12.0, ge=0)
    # [decision] 0: the cells within progress_clearance are walls (a GE in a corridor narrower
    # than twice the clearance cannot be reached); k >= 1: they are passable at k times the step
    # length, and only the cells within safety.d_min of a BZ or NFZ are walls
    progress_clearance_cost: float = Field(0.0, ge=0)

    @field_validator("progress_clearance_cost")
    @classmethod
    def _clearance_cost(cls, k: float) -> float:
        if 0 < k < 1:
            raise ValueError(f"reward.progress_clearance_cost must be 0 (walls) or >= 1, got {k}")
        return k

    @field_validator("sigma")
    @classmethod
    def _nonneg(cls, s: tuple[float, ...]) -> tuple[float, ...]:
        if any(v < 0 for v in s):
            raise ValueError(f"reward.sigma must be >= 0 element-wise, got {s}")
        return s


class CostConfig(StrictModel):
    """CPO cost c_t: weighted sum of event indicators (SPEC §7)."""

    boundary_exit: float = Field(1.0, ge=0)
    ou_collision: float = Field(1.0, ge=0)
    bz_collision: float = Field(1.0, ge=0)
    nfz_entry: float = Field(1.0, ge=0)
    # Beyond the paper, whose cost leaves the speed limit to r5: 0 keeps the paper's cost; a
    # positive weight makes RZ speeding a constraint for the constrained learners too.
    rz_speeding: float = Field(0.0, ge=0)


class SamplingConfig(StrictModel):
    grid_cell: float = Field(5.0, gt=0, le=5.0)  # occupancy grid for the connectivity check
    rect_tries: int = Field(200, ge=1)  # placements tried per rectangle
    point_tries: int = Field(200, ge=1)  # placements tried per GE / OU
    layout_tries: int = Field(50, ge=1)  # whole-layout resamples before giving up
    # Scenarios for partial resets are drawn from a pool sampled this many at a time: sampling
    # is vectorised, so one draw of 256 costs about as much as one draw of 1.
    pool_size: int = Field(256, ge=0)


class MapsConfig(StrictModel):
    """[decision] beyond SPEC §6, off by default: rasterised maps centred on the DCU appended to the
    flat observation (uavlae.envs.maps): a local fine one and a global coarse one, both square with
    an even number of cells per side, so that the DCU sits on the corner shared by the four central
    cells and the 90° rotations and the reflections map the grid onto itself."""

    enabled: bool = False
    local_size: int = Field(32, ge=2, le=256)  # cells per side
    local_cell: float = Field(2.0, gt=0)  # m: 32 x 2 m spans 64 m, the 20 m perception radius inside
    global_size: int = Field(16, ge=2, le=256)
    # m: 16 x 62.5 m spans 1000 m, twice the area's side: the whole area from anywhere in it
    global_cell: float = Field(62.5, gt=0)

    @field_validator("local_size", "global_size")
    @classmethod
    def _even(cls, n: int) -> int:
        if n % 2:
            raise ValueError(f"a map's cells per side must be even (the DCU on the centre corner), got {n}")
        return n


class EnvConfig(StrictModel):
    area: AreaConfig = AreaConfig()
    zones: ZonesConfig = ZonesConfig()
    ge: GEConfig = GEConfig()
    ou: OUConfig = OUConfig()
    motion: MotionConfig = MotionConfig()
    channel: ChannelConfig = ChannelConfig()
    energy: EnergyConfig = EnergyConfig()
    safety: SafetyConfig = SafetyConfig()
    reward: RewardConfig = RewardConfig()
    cost: CostConfig = CostConfig()
    sampling: SamplingConfig = SamplingConfig()
    t_max: int = Field(1000, ge=1)  # [decision] truncation
    terminate_on_collision: bool = True
    extra_features: bool = True  # [decision] distances to nearest BZ/NFZ/RZ/boundary/LA, in-RZ flag
    obs_distance_scale: float = Field(50.0, gt=0)  # obstacle distances in the observation saturate here
    # [decision] beyond SPEC §6, off by default: ego-centric columns (vector to the current
    # target and its direction, vectors to the nearest points of the nearest BZ and NFZ)
    ego_features: bool = False
    # [decision] beyond SPEC §6, world by default: the frame of the flat observation. "world" is
    # the paper's (absolute positions); "ego" gives every GE, zone, LA and the boundary relative to
    # the DCU (translated, axes still east/north: a heading is undefined while hovering, and the
    # action is a world-frame velocity), entities sorted by distance (ObservationLayout)
    obs_frame: Literal["world", "ego"] = "world"
    maps: MapsConfig = MapsConfig()

    @model_validator(mode="after")
    def _zones_fit(self) -> "EnvConfig":
        side = min(self.area.x_size, self.area.y_size)
        if self.zones.side_max > side:
            raise ValueError(
                f"zones.side_max={self.zones.side_max} is larger than the area "
                f"({self.area.x_size} x {self.area.y_size}); allowed range (0, {side}]"
            )
        return self


def make_env_config(cfg: Any = None, **overrides: Any) -> EnvConfig:
    """Build an :class:`EnvConfig` from a mapping / OmegaConf node / EnvConfig.

    Raises ``ValueError`` with the offending field path and message on bad input.
    """
    return parse_model(EnvConfig, cfg, prefix="env", title="environment", **overrides)
