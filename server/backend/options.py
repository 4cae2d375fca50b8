"""The back-end's options: one frozen dataclass per stage, composed into :class:`BackendOptions`.

The server's TOML sets them under ``[backend]`` (``enabled``, ``preset``, ``fix_scale``) and one table per
stage (``[backend.scheduler]``, ``[backend.placerec]``, ``[backend.accept]``, ``[backend.fit]``,
``[backend.optimise]``, ``[backend.gnss]``, ``[backend.gnss.stage]``, ``[backend.corrections]``,
``[backend.uncertainty]``). A preset
(:data:`PRESETS`) gives the starting values; the tables override single fields. Why each default is what
it is: ``docs/decisions.md``.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field, replace
from typing import Any

from hivemap.server.gnss_stage import GnssStageOptions
from hivemap.server.placerec import PlaceRecOptions, Thresholds


class ConfigError(ValueError):
    """A back-end option in the TOML is unknown or has the wrong type (the message names the key)."""


@dataclass(frozen=True)
class SchedulerOptions:
    """What runs when: the place-recognition queue (:mod:`~hivemap.server.backend.backlog`)."""

    queue_max: int = 5000  # queued query keyframes (oldest dropped beyond)
    # more waiting than this: keyframes whose place their agent has just queried are skipped (0: never)
    backlog: int = 10
    # where verification runs (:mod:`~hivemap.server.backend.executor`): "local" (worker processes),
    # "thread" (the place-recognition thread) or "ray" (Ray tasks; ray_address "" starts a local Ray)
    executor: str = "local"
    workers: int = 0  # processes / concurrent queries; 0: the cores less one, at least one
    ray_address: str = ""
    # each worker process keeps the features of this many keyframes it was sent, so that a job carries
    # only the others' (:mod:`~hivemap.server.placerec.shipping`; ~60 kB a keyframe); 0: every job
    # carries all of its keyframes' features
    worker_keyframe_cache: int = 3000


@dataclass(frozen=True)
class AcceptOptions:
    """Acceptance of detections (:mod:`hivemap.server.backend.accept`)."""

    # consecutive detections of one agent that must agree on the re-fitted transform
    consistency_required: int = 3
    consistency_max_gap: int = 8  # keyframe-id gap between consecutive consistent detections
    consistency_max_rot_deg: float = 2.0
    consistency_max_log_scale: float = 0.03
    consistency_max_rel_shift: float = 0.05  # query points moved / their spread
    min_pair_inlier_ratio: float = 0.5  # share of 3D pairs the trimmed fit must keep
    # metric maps: a loop asking for a larger correction of the query is a false match (also given to
    # place recognition, which rejects such candidates right after RANSAC)
    loop_max_correction_m: float = 1.0
    loop_max_correction_deg: float = 5.0
    # a loop whose rotation disagrees with both keyframes' IMU up directions by more is refused (0: off)
    loop_max_gravity_deg: float = 1.0
    # a merge stays on trial (undone if the robust pose graph rejects its edge) until this many loops
    # between its two sides, with distinct query keyframes, are kept alongside it
    merge_confirmations: int = 3
    # a new session whose first keyframe carries the agent's guess of its place in the previous session
    # is merged into that session's map by it, on trial (False: it waits for place recognition)
    session_guess: bool = True
    # ... or if one rigid alignment of the agents' GNSS fixes leaves a median residual this many times,
    # and at least this many metres, larger than each side's own alignment
    merge_gnss_factor: float = 3.0
    merge_gnss_min_m: float = 2.0
    # a merge contradicting the start prior overrides it only when this many independent places (no
    # shared map point on either side) agree on one transform, to within the error a merge may have
    prior_override_places: int = 3
    prior_override_max_m: float = 0.5
    prior_override_max_deg: float = 2.0


@dataclass(frozen=True)
class FitOptions:
    """How a loop's or merge's transform is fitted (:mod:`hivemap.server.backend.fit`)."""

    level_gravity: bool = True  # 4-DoF fit with roll/pitch from the keyframes' IMU up directions
    level_reprojection: bool = True  # then refine yaw and translation by bidirectional reprojection
    level_up_window: int = 6  # up directions averaged over +- this many keyframe ids (0: each its own)
    loop_sigma_bootstrap: int = 30  # resamples giving the edge's sigmas (0: the essential edges')
    # Weld (:mod:`~hivemap.server.backend.weld`): the fitted transform refined by stereo reprojection over
    # both covisible windows (this many keyframes a side) before the edge enters the graph; refused, with
    # its loop or merge, when the 99 % bound of its covariance exceeds these, or with fewer point pairs
    weld: bool = True
    weld_window: int = 5
    weld_max_bound_m: float = 0.5
    weld_max_bound_deg: float = 2.0
    weld_min_points: int = 20
    # 0: yaw and translation only (the levelled fit's tilt held); > 0: the tilt free within a prior of this
    # sigma (about the up directions' own error, which was most of what loops were off by); < 0: 6 DoF.
    # Without both keyframes' up directions the weld is 6 DoF.
    weld_tilt_sigma_deg: float = 0.2
    weld_compare: bool = False  # also solve the other variants and record them (measurement only)


@dataclass(frozen=True)
class OptimiseOptions:
    """Pose graph and global BA (:mod:`hivemap.server.backend.optimise`)."""

    # Global BA after each merge or loop and at an agent's mission end. A metric map's BA holds its scale
    # with the agents' stereo observations (none: no BA); the default preset leaves it off until it is
    # shown to help on the worlds of docs/decisions.md.
    global_ba: bool = False
    ba_max_keyframes: int = 4000
    ba_max_iterations: int = 30
    pose_graph_max_move_m: float = 3.0  # a pose graph moving any keyframe farther is refused
    pose_graph_sigma_rot: float = 0.01  # rad, essential edges
    pose_graph_sigma_trans: float = 0.05  # m, essential edges
    pose_graph_sigma_yaw: float = 0.0  # rad about the keyframe's up direction; 0: sigma_rot (isotropic)
    # The odometry edge across a stretch of weak or lost tracking is as sure as the odometry there: the
    # sigmas above or the drift over the path travelled (m per m, rad per rad), whichever is larger, plus,
    # in quadrature, the error the front-end reported (``Keyframe.odom_sigma``)
    pose_graph_drift_trans: float = 0.02
    pose_graph_drift_rot: float = 0.02
    # With ``gnc``, each agent's odometry edge between consecutive keyframes (its own relative pose) is as
    # sure as a floor plus, in quadrature, a random walk over the path travelled (sigma after 1 m of path,
    # growing with its square root, so a stretch is as sure whether it took few keyframes or many).
    odometry_sigma_m: float = 0.005
    odometry_sigma_deg: float = 0.03
    odometry_walk_m: float = 0.01
    odometry_walk_deg: float = 0.02
    # With ``pose_graph_tracked``, an agent's odometry edges are as sure as its tracking says
    # (``Keyframe.track_sigma``, summed along its keyframes) times the scale (the front-end's covariance is
    # its observations' alone, which the map points' own error adds to), at least the floors. Off: the
    # fixed sigmas above for every agent; on the worlds measured so far it did not change accuracy
    # beyond the runs' spread (docs/decisions.md), so it waits for the evidence.
    pose_graph_tracked: bool = False
    pose_graph_track_scale: float = 2.0
    pose_graph_track_floor_m: float = 0.002
    pose_graph_track_floor_deg: float = 0.02
    # Loop and merge edges are judged by graduated non-convexity (truncated least squares) at every pose
    # graph, all of a map's kept edges together: one the rest contradicts gets no weight and is reported
    # rejected (False: Huber, which still pulls).
    gnc: bool = True
    gnc_inlier_probability: float = 0.99


@dataclass(frozen=True)
class GnssOptions:
    """The server's GNSS stage and the GNSS-guided retry (:mod:`hivemap.server.backend.gnss`)."""

    enabled: bool = True
    # GNSS-guided retry (paper 2.5.3) between maps both in ENU: an agent's latest keyframe against the
    # other map's keyframes within this radius (0: off), at most once per map pair per interval
    retry_radius_m: float = 10.0
    retry_candidates: int = 6
    retry_interval_s: float = 5.0
    # a stage result is applied only when most fixes agree with the map
    max_rejected_ratio: float = 0.34
    max_median_residual_m: float = 0.5
    # the chain stiffness is cross-validated again once a map has this many and this share more fixes
    cv_new_fixes: int = 3
    cv_growth: float = 0.15
    stage: GnssStageOptions = GnssStageOptions()


@dataclass(frozen=True)
class CorrectionOptions:
    """What a correction to an agent carries (:mod:`hivemap.server.backend.corrections`)."""

    stride: int = 12  # every stride-th keyframe of the agent, plus the moved ones
    min_move_m: float = 0.01  # a keyframe is "moved" if it moved this much (local frame) ...
    min_rot_deg: float = 0.1  # ... or turned this much
    transform_window: int = 20  # recent keyframes whose corrections define an agent's new frame
    max_kfs: int = 50  # keyframes per correction (largest moves first): bounds the downlink


# The back-end confirms detections itself (AcceptOptions), so place recognition confirms every one.
_PLACEREC = PlaceRecOptions(consistency_required=1)


@dataclass(frozen=True)
class RendezvousOptions:
    """Rendezvous observations (:mod:`.rendezvous`): when they merge two maps, how their edges are
    weighted."""

    # a merge needs this many observations whose implied map-to-map transforms agree (chi-square gate on
    # each one's residual under their least-squares transform), spread over this many seconds
    min_observations: int = 3
    min_span_s: float = 1.0
    gate_chi2: float = 16.81  # 6 dof, 99 %
    # in that gate each observation's sigmas are at least these: the agents' own tracking drifts between
    # observations seconds apart by more than a close-range PnP's centimetres, while a wrong marker id is
    # off by the distance between two agents
    agree_sigma_rot_deg: float = 1.0
    agree_sigma_trans_m: float = 0.1
    # the agreement is sought among this many of the latest observations between two maps (it runs on the
    # event loop: each observation seeds a hypothesis)
    agree_window: int = 30
    # a detector on every other frame sees a carrier 10 times a second: one observation per observer and
    # observed agent per this many seconds (of data time) is used, the others are kept as ``redundant``;
    # and one agreement search per map pair per ``agree_interval_s`` (wall time)
    min_interval_s: float = 0.5
    agree_interval_s: float = 1.0
    # an edge within one map that the map already satisfies (chi-square at most this, the 6-dof median)
    # asks for no optimisation of its own: it is in the next one's robust graph. A hovering observer
    # otherwise had the map re-optimised, and every agent corrected, twice a second; < 0: every edge asks
    settled_chi2: float = 5.35
    # the observed agent's pose at the observation's time: interpolated between its keyframes; past its
    # last keyframe extrapolated at the last keyframes' velocity only this far, else held
    extrapolate_max_s: float = 0.3
    # the interpolation's uncertainty: this share of the bracketing keyframes' relative motion (at the
    # middle of the interval; extrapolation: of the motion beyond the last keyframe)
    interp_share: float = 0.2
    # floors of an edge's sigmas (a PnP covariance can be optimistic): its covariance's rotation and
    # translation eigenvalues are raised to them
    sigma_rot_floor_deg: float = 0.3
    sigma_trans_floor_m: float = 0.02
    # the observer's own error of its frame against its reference keyframe (``ref_from_cam``): its
    # front-end's drift over the path between them, in rotation (deg per m) and translation (m per m);
    # the rotation acts over the whole distance to the observed agent
    observer_drift_deg_per_m: float = 0.15
    observer_drift_trans: float = 0.02
    # the edge's tilt is updated with the two keyframes' IMU up directions (as loops and merges are
    # levelled), their relative tilt known to this sigma; 0: the PnP's tilt alone
    level_sigma_deg: float = 0.3
    # consecutive observations of one agent by one observer share much of their error (the same
    # carrier seen from a slowly changing viewpoint): each edge's covariance is multiplied by this, so
    # that a sighting of n edges weighs as n / correlated_edges observations (with a correlation rho
    # between them, n edges are worth at most 1 / rho independent ones)
    correlated_edges: float = 8.0


@dataclass(frozen=True)
class UncertaintyOptions:
    """Marginal covariances of the keyframes (:mod:`hivemap.server.backend.uncertainty`)."""

    enabled: bool = True
    # every keyframe's covariance of a map: at most once per this long ...
    min_interval_s: float = 1.0
    # ... and no sooner after the last than its CPU time / this share of a core
    max_duty: float = 0.2
    # ... or this share while place recognition has a backlog (more than ``scheduler.backlog`` queries
    # waiting): background work then leaves the core to the queries
    max_duty_behind: float = 0.03
    # maps with more keyframes get none (the cost of one solve: docs/decisions.md)
    max_keyframes: int = 20000
    # an agent's velocity (the collision advisories') is differenced from its latest keyframe and the newest
    # one at least this much older: over the 0.05-0.2 s between the keyframes of lost or weak tracking, the
    # difference divides an odometry edge's sigma (0.3 m after weak tracking) by that interval
    velocity_baseline_s: float = 1.0


@dataclass(frozen=True)
class BackendOptions:
    """Every back-end option; ``preset`` names the preset the values started from."""

    enabled: bool = True
    preset: str = "default"
    # Metric (stereo or stereo-inertial) agents: merges and loops are SE(3). False for monocular agents,
    # whose scale is a Sim(3) unknown.
    fix_scale: bool = True
    scheduler: SchedulerOptions = SchedulerOptions()
    placerec: PlaceRecOptions = field(default_factory=lambda: _PLACEREC)
    accept: AcceptOptions = AcceptOptions()
    fit: FitOptions = FitOptions()
    optimise: OptimiseOptions = OptimiseOptions()
    gnss: GnssOptions = GnssOptions()
    corrections: CorrectionOptions = CorrectionOptions()
    rendezvous: RendezvousOptions = RendezvousOptions()
    uncertainty: UncertaintyOptions = UncertaintyOptions()


PRESETS: dict[str, BackendOptions] = {
    "default": BackendOptions(),
    # monocular agents: Sim(3) merges and loops, and global BA (its residuals suit them)
    "monocular": BackendOptions(
        preset="monocular", fix_scale=False, optimise=OptimiseOptions(global_ba=True)
    ),
}


def preset(name: str = "default", **overrides: Any) -> BackendOptions:
    """The named preset with top-level fields or whole stage options replaced."""
    if name not in PRESETS:
        raise ConfigError(f"unknown back-end preset {name!r} (known: {', '.join(PRESETS)})")
    return replace(PRESETS[name], **overrides)


def _coerce(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        if isinstance(value, hint):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a table")
        return _update(hint(), value, where)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None and len(args) < len(typing.get_args(hint)):
            return None
        return _coerce(value, args[0], where)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected an array")
        item = typing.get_args(hint)[0]
        return tuple(_coerce(v, item, where) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported option type {hint!r}")


def _update(base: Any, table: dict[str, Any], where: str) -> Any:
    """``base`` (a frozen dataclass) with the fields in ``table`` replaced, recursively."""
    hints = typing.get_type_hints(type(base))
    names = {f.name for f in dataclasses.fields(base)}
    changes: dict[str, Any] = {}
    for key, value in table.items():
        if key not in names:
            raise ConfigError(f"unknown key {where}.{key}")
        current = getattr(base, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[key] = _update(current, value, f"{where}.{key}")
        else:
            changes[key] = _coerce(value, hints[key], f"{where}.{key}")
    return replace(base, **changes)


def from_table(table: dict[str, Any] | bool | BackendOptions | None) -> BackendOptions:
    """The options a TOML ``[backend]`` table asks for: its ``preset`` (default ``"default"``) with the
    table's fields replaced. ``true``/``false`` alone only switch the back-end on or off (older configs);
    unknown keys raise :class:`ConfigError` naming the key."""
    if table is None:
        return PRESETS["default"]
    if isinstance(table, BackendOptions):
        return table
    if isinstance(table, bool):
        return replace(PRESETS["default"], enabled=table)
    if not isinstance(table, dict):
        raise ConfigError(f"backend: expected a table or true/false, got {table!r}")
    name = table.get("preset", "default")
    if not isinstance(name, str):
        raise ConfigError(f"backend.preset: expected a string, got {name!r}")
    return _update(preset(name), {k: v for k, v in table.items() if k != "preset"}, "backend")


def to_table(options: BackendOptions) -> dict[str, Any]:
    """``options`` as the nested table :func:`from_table` reads back (tuples as lists)."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v

    out: dict[str, Any] = plain(options)
    return out


__all__ = [
    "PRESETS",
    "AcceptOptions",
    "BackendOptions",
    "ConfigError",
    "CorrectionOptions",
    "FitOptions",
    "GnssOptions",
    "GnssStageOptions",
    "OptimiseOptions",
    "PlaceRecOptions",
    "RendezvousOptions",
    "SchedulerOptions",
    "Thresholds",
    "UncertaintyOptions",
    "from_table",
    "preset",
    "to_table",
]
