"""Options of the team services (frontiers, auction, ORCA advisories, follow-the-leader): one frozen
dataclass per job, composed into :class:`TeamOptions`, set by the server's ``[team]`` TOML table
(``[team.frontiers]``, ``[team.auction]``, ``[team.orca]``, ``[team.follow]``).

Heights are along the map frame's z axis, taken to point up: the agents' VIO frames are gravity-aligned
when they use their IMU, and so are the maps merged from them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# The back-end's loader already checks types and names unknown keys; its options are frozen dataclasses
# too, so the same function reads these.
from hivemap.server.backend.options import ConfigError
from hivemap.server.backend.options import _update as _update_dataclass
from hivemap.server.backend.options import to_table as _to_table


@dataclass(frozen=True)
class FrontierOptions:
    """Frontier extraction from a map's points (:mod:`.frontiers`)."""

    voxel_m: float = 0.5  # down-sampling voxel, also the ground grid's cell
    # the explored region's small gaps (a sparse map has them) are closed by this many cells before its
    # boundary is taken; 0: none
    close_cells: int = 1
    # boundary cells are grouped by 8-connectivity, then split into tiles of this size so that a long
    # boundary gives several goals; groups with fewer frontier points are dropped
    cluster_m: float = 4.0
    min_cluster_points: int = 3
    # the ground plane: fitted to the points within ground_band_m above this percentile of heights
    ground_percentile: float = 5.0
    ground_band_m: float = 0.3
    # a frontier is reachable by a kind when one of its points lies within the kind's height band above
    # the ground plane: a UGV sees what is near the ground, a UAV what lies within its altitude band
    ugv_max_height_m: float = 0.5
    uav_min_alt_m: float = 1.0
    uav_max_alt_m: float = 8.0
    max_points: int = 200_000  # an even subsample of a larger map is used (bounds the time per map)
    # lines of sight: up to this many per keyframe (from its camera to points it observed, evenly chosen)
    # mark the ground they cross as explored, up to view_range_m from the camera; 0: none
    view_rays: int = 16
    view_range_m: float = 20.0


@dataclass(frozen=True)
class AuctionOptions:
    """The sequential single-item auction (:mod:`.auction`)."""

    max_goals_per_agent: int = 5  # 0: no cap
    # uncertainty-aware variant: a bid is the added path cost less this many metres per nat of expected
    # uncertainty reduction (:func:`.auction.d_optimal_gain`); 0: plain added path cost
    uncertainty_weight_m: float = 0.0
    # the gain's model: each map point near a goal is an isotropic position fix of this sigma
    fix_sigma_m: float = 0.5
    gain_radius_m: float = 3.0  # map points within this of the goal count
    max_fixes: int = 50  # at most this many (the fixes are not independent: a cap keeps it a proxy)
    # goal commitment (:mod:`.commit`): an agent keeps its first goal while a frontier it may take lies
    # within held_match_m of it (a frontier's goal moves within its cluster tile as the map grows), until
    # it comes within held_reached_m, stands still (moves less than held_progress_m) for held_idle_s, or
    # for held_stall_s it got no held_progress_m nearer (all in mission time)
    held_match_m: float = 4.0
    held_reached_m: float = 2.0
    held_idle_s: float = 5.0
    held_stall_s: float = 20.0
    held_progress_m: float = 1.0
    # a goal given up is not offered to the same agent again for this long (mission time)
    dropped_memory_s: float = 30.0


@dataclass(frozen=True)
class OrcaOptions:
    """ORCA collision advisories (:mod:`.orca`)."""

    time_horizon_s: float = 5.0  # velocities are collision-free for this long
    time_step_s: float = 0.5  # the advisory period (ORCA resolves overlaps within one step)
    neighbor_dist_m: float = 20.0
    max_neighbors: int = 10
    radius_uav_m: float = 0.5
    radius_ugv_m: float = 0.8
    # the agents' own half heights about their camera: ORCA's cylinders are these high, inflated by the
    # vertical uncertainty (not by the horizontal radius: a UGV's horizontal error says nothing of a UAV
    # above it)
    half_height_uav_m: float = 0.3
    half_height_ugv_m: float = 1.0
    max_speed_uav: float = 2.0  # m/s; also the cruise speed of the desired velocity towards a goal
    max_speed_ugv: float = 1.0
    # without an intent from the agent, one faster than this keeps its current velocity as ORCA's preferred
    # one (orca.preferred_velocity)
    moving_mps: float = 0.2
    # inflation: radius + k_sigma * (position sigma + velocity_horizon_s * sqrt(max eigenvalue of the
    # velocity's horizontal covariance)); the position sigma is the agent's largest share of its relative
    # sigmas to the map's other agents (orca.position_sigma)
    k_sigma: float = 2.0
    velocity_horizon_s: float = 1.0
    # without a covariance from the server's graph, these sigmas (per horizontal axis) are assumed
    default_position_sigma_m: float = 0.1
    default_velocity_sigma_mps: float = 0.05
    # neighbours are carried at their velocities to the time of the advised agent's position, at most
    # this far (a keyframe much older than the others says little of where its agent is now)
    max_predict_s: float = 3.0
    # the agents reach a new velocity over a second or two, not at once as ORCA assumes, and fall behind
    # the path it planned by up to about this: ORCA keeps this much more apart than the inflated radii
    # (the tracking error bound epsilon of Alonso-Mora et al.'s NH-ORCA); the reported radius excludes it
    tracking_margin_m: float = 0.5


@dataclass(frozen=True)
class FollowOptions:
    """Follow-the-leader reference paths (:mod:`.follow`)."""

    distance_m: float = 3.0  # arc length behind the leader along its path
    spacing_m: float = 0.25  # spacing of the reference path's points


@dataclass(frozen=True)
class TeamOptions:
    """Every team-service option."""

    enabled: bool = True
    # frontiers and assignments are recomputed at most once per this many seconds (per map / team)
    min_interval_s: float = 2.0
    # agents whose hello asked for them get a ``team_advisory`` this often (protocol v4)
    push_interval_s: float = 1.0
    frontiers: FrontierOptions = FrontierOptions()
    auction: AuctionOptions = AuctionOptions()
    orca: OrcaOptions = OrcaOptions()
    follow: FollowOptions = FollowOptions()


def from_table(table: dict[str, Any] | bool | TeamOptions | None) -> TeamOptions:
    """The options a TOML ``[team]`` table asks for (defaults for the fields it leaves out); ``true`` /
    ``false`` alone switch the services on or off. Unknown keys raise :class:`ConfigError` naming them."""
    if table is None:
        return TeamOptions()
    if isinstance(table, TeamOptions):
        return table
    if isinstance(table, bool):
        return TeamOptions(enabled=table)
    if not isinstance(table, dict):
        raise ConfigError(f"team: expected a table or true/false, got {table!r}")
    out: TeamOptions = _update_dataclass(TeamOptions(), table, "team")
    return out


def to_table(options: TeamOptions) -> dict[str, Any]:
    """``options`` as the nested table :func:`from_table` reads back."""
    return _to_table(options)  # type: ignore[arg-type]


__all__ = [
    "AuctionOptions",
    "ConfigError",
    "FollowOptions",
    "FrontierOptions",
    "OrcaOptions",
    "TeamOptions",
    "from_table",
    "to_table",
]
