"""When could each agent's camera see each other agent's marker carrier? Geometry only, no rendering.

For every camera frame (10 Hz) and ordered pair (observer, carrier agent) a marker counts as seen when its
four corners are in front of the camera and inside the image (distortion included), it faces the camera
(viewing angle < 75 deg), no building or obstacle lies on the line of sight, and its projected side is at
least ``--min-px`` pixels. Prints, per design and world seed, the seconds seen in the first 15 s after
take-off and overall, the distance range and the median pixel side of the largest seen marker.

Run: .venv/bin/python bench/marker_visibility.py [--seeds default,1,2,3] [--scenario factory01]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from hivemap.sim.carriers import CODE_CELLS, FACE_CELLS, SMALL_ROOF_ROWS_X, CarrierDesign, team_geometry
from hivemap.sim.dataset import cached_world, stereo_extrinsics
from hivemap.sim.scenario_file import resolve_scenario
from hivemap.sim.scenarios import UGV_ROOF_HEIGHT
from hivemap.sim.takeoff import takeoff_plan
from hivemap.sim.trajectories import plan_trajectories

DESIGNS = {
    "cube30+roof1x2": CarrierDesign(ugv_back=False, ugv_sides=False),
    "cube20+roof1x2": CarrierDesign(uav_cube_m=0.20, ugv_back=False, ugv_sides=False),
    "cube40+roof1x2": CarrierDesign(uav_cube_m=0.40, ugv_back=False, ugv_sides=False),
    "cube30+roof2x2": CarrierDesign(ugv_rows_x=(-0.65, 0.65), ugv_back=False, ugv_sides=False),
    "cube30+roof1x2+back60": CarrierDesign(ugv_sides=False, ugv_panel_m=0.6),
    "chosen: cube30+roof1x2+back70+sides70": CarrierDesign(),
    "cube30+roof1x2+back70+sides70+roof small 4x2": CarrierDesign(ugv_small_rows_x=SMALL_ROOF_ROWS_X),
}
RATE_HZ = 10.0
WINDOW_S = 15.0


def _occluded(world, a: np.ndarray, b: np.ndarray) -> bool:
    n = max(2, int(np.linalg.norm(b - a) / 0.25))
    s = np.linspace(0.05, 0.95, n)
    pts = a[None] + s[:, None] * (b - a)[None]
    for box in world.boxes:
        top = float(box.center[2] + box.size[2] / 2)
        low = pts[:, 2] < top
        if low.any() and box.contains_xy(pts[low, :2]).any():
            return True
    return False


def visibility(scenario, design: CarrierDesign, min_px: float) -> dict[tuple[str, str], dict[str, list]]:
    world = cached_world(scenario.seed, scenario.world_size_m)
    plan = plan_trajectories(world, scenario)
    cam = scenario.camera.pinhole()
    geo = team_geometry(scenario, design)
    ext = {a.agent_id: stereo_extrinsics(a)[0] for a in scenario.agents}
    dur = min(t.duration for t in plan.trajectories.values())
    if scenario.duration_s is not None:
        dur = min(dur, scenario.duration_s)
    t = np.arange(0.0, dur, 1.0 / RATE_HZ)
    W = {k: tr.world_from_body(t) for k, tr in plan.trajectories.items()}
    out: dict[tuple[str, str], dict[str, list]] = {}
    for o in W:
        for c in W:
            if o == c:
                continue
            rec: dict[str, list] = {"t": [], "dist": [], "px": []}
            faces = geo[c].faces  # (F, 4, 3) body
            marker = faces.mean(1)[:, None] + (faces - faces.mean(1)[:, None]) * (CODE_CELLS / FACE_CELLS)
            for i, ti in enumerate(t):
                wc = W[o][i] @ ext[o]
                cam_from_world = np.linalg.inv(wc)
                Wb = W[c][i]
                pw = marker.reshape(-1, 3) @ Wb[:3, :3].T + Wb[:3, 3]
                if (
                    geo[c].kind == "uav"
                    and float((faces @ Wb[:3, :3].T + Wb[:3, 3])[..., 2].min()) < UGV_ROOF_HEIGHT
                ):
                    continue  # docked: not drawn (CarrierScene)
                pc = pw @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
                pc = pc.reshape(len(faces), 4, 3)
                centre_w = pw.reshape(len(faces), 4, 3).mean(1)
                best = 0.0
                for f in range(len(faces)):
                    if (pc[f, :, 2] < 0.2).any():
                        continue
                    uv, ok = cam.project(pc[f])
                    if not ok.all() or not cam.in_image(uv, 2.0).all():
                        continue
                    nrm = np.cross(pc[f, 1] - pc[f, 0], pc[f, 3] - pc[f, 0])
                    view = -pc[f].mean(0)
                    cosang = float(nrm @ view / (np.linalg.norm(nrm) * np.linalg.norm(view)))
                    if cosang < np.cos(np.radians(75.0)):
                        continue
                    e = np.diff(np.vstack([uv, uv[:1]]), axis=0)
                    side = float(np.linalg.norm(e, axis=1).min())
                    if side < min_px or side <= best:
                        continue
                    if _occluded(world, wc[:3, 3], centre_w[f]):
                        continue
                    best = side
                if best > 0:
                    rec["t"].append(float(ti))
                    rec["dist"].append(float(np.linalg.norm(Wb[:3, 3] - wc[:3, 3])))
                    rec["px"].append(best)
            out[(o, c)] = rec
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="factory01")
    ap.add_argument("--seeds", default="default,1,2,3")
    ap.add_argument("--designs", default=",".join(DESIGNS), help="comma-separated, names as in DESIGNS")
    ap.add_argument("--min-px", type=float, default=20.0)
    ap.add_argument("--takeoff-interval", type=float, default=0.0, help="Scenario.takeoff_interval_s")
    ap.add_argument("--takeoff-climb", type=float, default=0.0, help="Scenario.takeoff_climb_m")
    args = ap.parse_args()
    for seed in args.seeds.split(","):
        sc = resolve_scenario(args.scenario, None if seed == "default" else int(seed))
        sc = dataclasses.replace(
            sc, takeoff_interval_s=args.takeoff_interval, takeoff_climb_m=args.takeoff_climb
        )
        leave = {k: v.leave_t for k, v in takeoff_plan(sc).items()}
        for name in args.designs.split(","):
            vis = visibility(sc, DESIGNS[name], args.min_px)
            head = f"{args.scenario} seed {seed} (world {sc.seed}), design {name}"
            print(
                f"\n## {head}, take-off interval {args.takeoff_interval:g} s, climb {args.takeoff_climb:g} m"
            )
            print(
                "| observer -> carrier | s seen in the pair's first 15 s | s seen overall | first seen (s) "
                "| distance (m) | px (median) |"
            )
            print("|---|---|---|---|---|---|")
            for (o, c), r in vis.items():
                tt = np.asarray(r["t"])
                if len(tt) == 0:
                    continue
                # the window starts when the later of the two leaves its start
                t_off = max(leave[o], leave[c])
                early = float(((tt >= t_off) & (tt < t_off + WINDOW_S)).sum()) / RATE_HZ
                d = np.asarray(r["dist"])
                print(
                    f"| {o} -> {c} | {early:.1f} | {len(tt) / RATE_HZ:.1f} | {tt[0]:.1f} | "
                    f"{d.min():.1f}-{d.max():.1f} | {np.median(r['px']):.0f} |"
                )


if __name__ == "__main__":
    main()
