"""Server settings: pydantic-settings ``BaseSettings`` (env prefix ``HIVEMAP_``) plus an optional TOML file.

Precedence (highest first): explicit overrides (CLI flags), environment variables, the TOML file, defaults.

Example TOML::

    host = "0.0.0.0"
    port = 8765
    data_dir = "/data/server"

    [tokens]
    uav1 = "secret-uav1"
    ugv1 = "secret-ugv1"

    [quotas]                  # per agent; see QuotaSettings
    max_points = 300000
    points_per_s = 5000
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from hivemap.server.backend.options import BackendOptions
from hivemap.server.backend.options import from_table as backend_options_from_table
from hivemap.server.team.options import TeamOptions
from hivemap.server.team.options import from_table as team_options_from_table


class QuotaSettings(BaseModel):
    """Per-agent limits (the ``[quotas]`` table). The totals bound what one agent can make the server
    hold in memory: the stack keeps every stored point and keyframe, so ``max_points`` and
    ``max_keyframes`` times the agent count is the server's memory bound (see the README). The rates
    are token buckets (``*_per_s`` refill, ``*_burst`` capacity): an agent resending an outage's
    backlog fits in the burst. Defaults are ~10x what a 90 s factory01 agent stores (~700 keyframes,
    ~30k points) and ~10x its rates."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_points: int = Field(default=300_000, ge=1, description="Map points stored per agent, in total.")
    max_keyframes: int = Field(default=5_000, ge=1, description="Keyframes stored per agent, in total.")
    points_per_s: float = Field(default=5000.0, gt=0.0, description="Sustained map points per second.")
    points_burst: int = Field(default=50_000, ge=1, description="Map points accepted at once above the rate.")
    keyframes_per_s: float = Field(default=50.0, gt=0.0, description="Sustained keyframes per second.")
    keyframes_burst: int = Field(default=500, ge=1, description="Keyframes accepted at once above the rate.")


class StartPoses(BaseModel):
    """The ``[start_poses]`` table: ``sigma_m``, ``sigma_deg`` (the mounting's uncertainty, per axis) and
    one 4x4 cam0 start pose per agent (``uav1 = [[...], ...]``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    sigma_m: float = Field(default=0.2, gt=0.0, description="Start position uncertainty per axis (m).")
    sigma_deg: float = Field(default=5.0, gt=0.0, description="Start orientation uncertainty per axis (deg).")
    poses: dict[str, list[list[float]]] = Field(default_factory=dict)

    @field_validator("poses")
    @classmethod
    def _rigid_4x4(cls, v: dict[str, list[list[float]]]) -> dict[str, list[list[float]]]:
        import numpy as np

        for agent, T in v.items():
            M = np.asarray(T, dtype=np.float64)
            if M.shape != (4, 4) or not np.isfinite(M).all():
                raise ValueError(f"start_poses.{agent}: expected a finite 4x4 matrix, got shape {M.shape}")
            R = M[:3, :3]
            if not np.allclose(M[3], [0, 0, 0, 1]) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
                raise ValueError(
                    f"start_poses.{agent}: not a rigid transform (rotation and last row [0 0 0 1])"
                )
        return v


class ServerSettings(BaseSettings):
    """Everything the server needs; built once and handed to :func:`hivemap.server.app.create_app`."""

    model_config = SettingsConfigDict(env_prefix="HIVEMAP_", extra="forbid", env_nested_delimiter="__")

    host: str = "127.0.0.1"
    port: int = Field(default=8765, ge=0, le=65535)
    data_dir: Path = Path("hivemap-data")
    tokens: dict[str, str] = Field(
        default_factory=dict, description="Per-agent tokens (agent id -> token); others are refused."
    )
    start_poses: StartPoses = Field(
        default_factory=lambda: StartPoses(),
        description=(
            "Nominal start configuration (paper 2.4: the UAVs take off from the UGV's roof): agent id -> 4x4 "
            "pose of the agent's cam0 at its start, in any common frame, known to sigma_m / sigma_deg. A "
            "prior for place recognition between those agents' maps, never a merge by itself."
        ),
    )

    @field_validator("start_poses", mode="before")
    @classmethod
    def _start_table(cls, v: Any) -> Any:
        # the TOML table mixes the two sigmas with one pose per agent
        if isinstance(v, dict) and "poses" not in v:
            v = dict(v)
            sig = {k: v.pop(k) for k in ("sigma_m", "sigma_deg") if k in v}
            return {**sig, "poses": v}
        return v

    # Ingest and back-pressure.
    max_frame_bytes: int = Field(
        default=4 * 1024 * 1024, ge=1024, description="Largest WebSocket frame accepted."
    )
    ws_max_queue: int = Field(
        default=16, ge=1, description="Frames buffered by the WebSocket server per connection."
    )
    outbox_max: int = Field(
        default=1024, ge=8, description="Outgoing messages queued per connection (then dropped)."
    )
    max_uncommitted: int = Field(
        default=512,
        ge=1,
        description="Messages applied but not committed (server-wide) before readers pause.",
    )
    max_pending_keyframes: int = Field(
        default=500, ge=1, description="Keyframes per agent waiting for their map points (more are refused)."
    )
    commit_interval_ms: float = Field(
        default=5.0, ge=0.0, description="Group-commit window of the SQLite writer."
    )
    sqlite_synchronous: Literal["FULL", "NORMAL"] = Field(
        default="FULL", description="FULL survives power loss, NORMAL (WAL) survives a process crash."
    )
    per_message_deflate: bool = False
    quotas: QuotaSettings = Field(default_factory=QuotaSettings)
    hello_timeout_s: float = Field(
        default=10.0, gt=0.0, description="A connection that sends no hello within this is closed."
    )
    hello_loading_wait_s: float = Field(
        default=3.0,
        ge=0.0,
        description="A hello while the store loads waits this long for it, then is told to retry.",
    )
    max_seq_step: int = Field(
        default=10_000,
        ge=1,
        description="Largest seq increase per message; a frame jumping further is refused (field 'seq').",
    )
    shutdown_timeout_s: float = Field(
        default=10.0, gt=0.0, description="On SIGTERM/SIGINT: wait this long for connections to finish."
    )
    backend: BackendOptions = Field(
        default_factory=BackendOptions,
        description="The collaboration back-end (merging, loops): [backend] enabled, preset, stage tables.",
    )
    team: TeamOptions = Field(
        default_factory=TeamOptions,
        description="Team services (frontiers, auction, ORCA advisories): [team] and its stage tables.",
    )
    foxglove_port: int | None = Field(
        default=None, ge=0, le=65535, description="Publish the mission on a Foxglove WebSocket on this port."
    )
    groundtruth: Path | None = Field(
        default=None,
        description=(
            "Ground truth for the viewer (evaluations): a folder with DIR/<agent>/mav0/"
            "state_groundtruth_estimate0/data.csv (a rendered scenario) or DIR/<agent>.tum per agent."
        ),
    )
    # Inspection.
    event_buffer: int = Field(default=10000, ge=10, description="Events kept in the /events ring buffer.")
    ping_interval_s: float = Field(default=20.0, gt=0.0)
    log_level: str = "info"

    @field_validator("groundtruth")
    @classmethod
    def _groundtruth_folder(cls, v: Path | None) -> Path | None:
        if v is not None and not v.is_dir():
            raise ValueError(f"{v} is not a folder")
        return v

    @field_validator("backend", mode="before")
    @classmethod
    def _backend_options(cls, v: Any) -> BackendOptions:
        return backend_options_from_table(v)  # ConfigError (a ValueError) names an unknown key

    @field_validator("team", mode="before")
    @classmethod
    def _team_options(cls, v: Any) -> TeamOptions:
        return team_options_from_table(v)


def load_settings(config: Path | None = None, **overrides: Any) -> ServerSettings:
    """Settings from a TOML file (optional), the environment and explicit ``overrides`` (None = unset)."""
    file_values: dict[str, Any] = {}
    if config is not None:
        with open(config, "rb") as f:
            file_values = tomllib.load(f)
    from_env = ServerSettings()
    env_values = from_env.model_dump(include=from_env.model_fields_set)
    explicit = {k: v for k, v in overrides.items() if v is not None}
    return ServerSettings(**{**file_values, **env_values, **explicit})
