"""The co-location server's ``[start_poses]`` table for an experiment run (issue 27): the agents' nominal
mounting (paper 2.4: the UAVs take off from the UGV's roof) as a prior with stated uncertainty.

Modes: ``perturbed`` (default) each agent's true cam0 start pose moved by a seeded draw of the sigmas
(per axis: position in the world, orientation about the camera's own axes), as a measured mounting
would be; ``none`` no table (place recognition alone); ``truth`` the simulation's exact start poses
(only on explicit request: it hides how merges do without ground truth).
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

START_POSE_MODES = ("perturbed", "none", "truth")


@dataclass(frozen=True)
class StartPoseOptions:
    mode: str = "perturbed"
    sigma_m: float = 0.2
    sigma_deg: float = 5.0
    seed: int = 0  # with the world's seed and the agent's id: the draw of each agent's offset

    def __post_init__(self) -> None:
        if self.mode not in START_POSE_MODES:
            raise ValueError(
                f"unknown start poses {self.mode!r}; expected one of {', '.join(START_POSE_MODES)}"
            )


def start_poses(
    scen: Path, agent_ids: Sequence[str], o: StartPoseOptions, world_seed: int | None
) -> dict[str, Any]:
    """What the run gives the server: ``poses`` (agent -> 4x4, none in mode ``none``) and per agent the
    ``offsets`` (m, deg) of its nominal pose from the truth, with the mode and sigmas."""
    import numpy as np

    from hivemap.client.dataset import load_scenario

    if o.mode == "none":
        return start_poses_from({}, o, world_seed)
    scenario = load_scenario(scen)
    truth = {}
    for a in agent_ids:
        ds = scenario.load_agent(a)
        truth[a] = np.asarray(ds.groundtruth.world_from_body[0]) @ np.asarray(ds.T_BS["cam0"])
    return start_poses_from(truth, o, world_seed)


def start_poses_from(truth: dict[str, Any], o: StartPoseOptions, world_seed: int | None) -> dict[str, Any]:
    """:func:`start_poses` from the agents' true cam0 start poses (agent -> 4x4), e.g. live agents'."""
    import numpy as np

    from hivemap.maps.geometry import rotation_angle_deg, se3, so3_exp

    out: dict[str, Any] = {"mode": o.mode, "sigma_m": o.sigma_m, "sigma_deg": o.sigma_deg, "seed": o.seed,
                           "poses": {}, "offsets": {}}  # fmt: skip
    if o.mode == "none":
        return out
    for a, T_true in truth.items():
        T = np.asarray(T_true, dtype=np.float64)
        if o.mode == "perturbed":
            rng = np.random.default_rng([o.seed, int(world_seed or 0), zlib.crc32(a.encode())])
            dR = so3_exp(np.radians(o.sigma_deg) * rng.standard_normal(3))
            dt = o.sigma_m * rng.standard_normal(3)
            T_nom = se3(T[:3, :3] @ dR, T[:3, 3] + dt)
            out["offsets"][a] = {"m": float(np.linalg.norm(dt)), "deg": rotation_angle_deg(dR)}
        else:
            T_nom = T
            out["offsets"][a] = {"m": 0.0, "deg": 0.0}
        out["poses"][a] = [[float(x) for x in row] for row in T_nom]
    return out


def start_poses_toml(table: dict[str, Any]) -> str:
    """The ``[start_poses]`` TOML table of :func:`start_poses` (empty in mode ``none``)."""
    if not table["poses"]:
        return ""
    lines = [
        "[start_poses]\n",
        f"sigma_m = {float(table['sigma_m'])}\n",
        f"sigma_deg = {float(table['sigma_deg'])}\n",
    ]
    lines += [f"{a} = {T}\n" for a, T in table["poses"].items()]
    return "".join(lines)


def describe(table: dict[str, Any] | None) -> str:
    """One line for the report: which start poses the server had."""
    if not table:
        return "start poses: not recorded (a run from before issue 27: the true start poses, taken as exact)"
    if table["mode"] == "none":
        return "start poses: none (merges by place recognition alone)"
    offs = table.get("offsets") or {}
    worst = (
        max((v["m"] for v in offs.values()), default=0.0),
        max((v["deg"] for v in offs.values()), default=0.0),
    )
    what = "the true ones" if table["mode"] == "truth" else f"the true ones perturbed (seed {table['seed']})"
    return (f"start poses: {what}, stated sigma {table['sigma_m']} m / {table['sigma_deg']} deg per axis; "
            f"largest offset from the truth {worst[0]:.2f} m / {worst[1]:.1f} deg; "
            + ", ".join(f"{a} {v['m']:.2f} m {v['deg']:.1f} deg" for a, v in offs.items()))  # fmt: skip
