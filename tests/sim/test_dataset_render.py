"""Rendered datasets: written and read back equal, stereo/ground-truth consistency, resume, CLI."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from hivemap.client.dataset import load_dataset, load_scenario
from hivemap.sim.dataset import COMPLETE_MARK, cached_world, render_scenario, stereo_extrinsics
from hivemap.sim.scenarios import get_scenario
from hivemap.sim.sensors import simulate_gnss, simulate_imu

DURATION = 4.0
AGENTS = ["uav1", "ugv"]


@pytest.fixture(scope="module")
def world():
    sc = get_scenario("tiny")
    return cached_world(sc.seed, sc.world_size_m)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory, world):
    out = tmp_path_factory.mktemp("tiny")
    res = render_scenario(
        get_scenario("tiny"), out, agents=AGENTS, duration=DURATION, progress=False, world=world
    )
    return out, res


def test_written_and_read_back_equal(rendered):
    out, res = rendered
    sc = replace(get_scenario("tiny"), duration_s=DURATION)
    man = load_scenario(out)
    assert man.name == "tiny" and [a.id for a in man.agents] == AGENTS
    assert man.origin == (sc.origin_lat, sc.origin_lon, sc.origin_alt)
    for idx, spec in enumerate(sc.agents):
        if spec.agent_id not in AGENTS:
            continue
        traj = res.plan.trajectories[spec.agent_id]
        ds = man.load_agent(spec.agent_id)
        assert (ds.agent_id, ds.kind) == (spec.agent_id, spec.kind)
        # frames: 10 Hz from 0 to DURATION, stereo, intrinsics as the preset
        assert len(ds.frames) == int(DURATION * sc.camera.rate_hz) + 1
        assert ds.cameras["cam0"] == sc.camera.pinhole() == ds.cameras["cam1"]
        T0, T1 = stereo_extrinsics(spec)
        assert np.allclose(ds.T_BS["cam0"], T0, atol=1e-12) and np.allclose(ds.T_BS["cam1"], T1, atol=1e-12)
        assert ds.rig is not None and ds.rig.baseline == pytest.approx(spec.baseline_m, abs=1e-9)
        g0, g1 = ds.frames.load(len(ds.frames) - 1)
        assert g0.shape == (sc.camera.height, sc.camera.width) and g1 is not None
        # IMU and GNSS: exactly the simulated samples (same seed streams), floats written losslessly
        imu = simulate_imu(
            traj, sc.imu_rate_hz, sc.imu_noise, np.random.default_rng([sc.seed, idx, 1]), DURATION
        )
        assert np.array_equal(ds.imu[:, 1:4], imu.gyro) and np.array_equal(ds.imu[:, 4:7], imu.accel)
        assert np.array_equal(ds.imu_t_ns, sc.start_time_ns + np.round(imu.t * 1e9).astype(np.int64))
        gn = simulate_gnss(
            traj, sc.gnss_rate_hz, sc.gnss_noise, np.random.default_rng([sc.seed, idx, 2]), DURATION
        )
        assert ds.gnss is not None and np.array_equal(ds.gnss.enu, gn.enu)
        assert np.allclose(ds.gnss.sigma, [0.05, 0.15])
        # ground truth = trajectory poses (quaternion round trip ~1e-15)
        gt = ds.groundtruth
        assert gt is not None
        t_s = (gt.t_ns - sc.start_time_ns) * 1e-9
        assert np.allclose(gt.world_from_body, traj.world_from_body(t_s), atol=1e-9)
        assert np.allclose(gt.velocity, traj.velocity(t_s), atol=1e-12)
        assert np.array_equal(gt.bias_gyro, imu.bias_gyro)
        # camera-rate ground truth = rows of the IMU-rate one (camera stamps are IMU stamps)
        assert np.allclose(
            ds.groundtruth_at_frames(), traj.world_from_body(ds.frames.timestamps - ds.frames.timestamps[0])
        )


def test_stereo_and_groundtruth_consistency(rendered, world):
    # Re-render depth at dataset poses: a cam0 pixel with depth z, moved through the rig read from the
    # sensor.yaml files, must land in cam1 at disparity f*b/z and where cam1's depth agrees.
    from hivemap.sim.render import make_renderer

    out, _ = rendered
    for agent in AGENTS:
        ds = load_dataset(out / agent)
        rig = ds.rig
        assert rig is not None
        cam = rig.left
        W = ds.groundtruth_at_frames()[-1]
        r = make_renderer(world, cam, backend="auto")
        try:
            _, d0 = r.render(W @ ds.T_BS["cam0"])
            _, d1 = r.render(W @ ds.T_BS["cam1"])
        finally:
            r.close()
        rng = np.random.default_rng(0)
        uv = np.stack([rng.uniform(5, cam.width - 6, 4000), rng.uniform(5, cam.height - 6, 4000)], axis=1)
        z = d0[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
        uv = np.round(uv)
        ok = np.isfinite(z) & (z < 80)
        uv, z = uv[ok], z[ok].astype(np.float64)
        xy = cam.undistort_to_normalized(uv)
        P0 = np.concatenate([xy * z[:, None], z[:, None]], axis=1)
        R, t = rig.right_from_left[:3, :3], rig.right_from_left[:3, 3]
        P1 = P0 @ R.T + t
        # undistorted disparity = f * b / z
        x1 = P1[:, 0] / P1[:, 2]
        assert np.allclose(cam.fx * (xy[:, 0] - x1), cam.fx * rig.baseline / z, rtol=1e-9)
        uv1, valid = rig.right.project(P1)
        inside = valid & rig.right.in_image(uv1, margin=1)
        assert inside.mean() > 0.8
        iu = np.round(uv1[inside]).astype(int)
        z1 = d1[iu[:, 1], iu[:, 0]]
        rel = np.abs(z1 - P1[inside, 2]) / P1[inside, 2]
        # occlusion edges differ between the two views: >= 95 % of points agree to 1 %
        assert np.mean(rel < 0.01) > 0.95, agent


def test_resume_renders_only_missing_frames(rendered, world, tmp_path):
    out, _ = rendered
    dst = tmp_path / "copy"
    shutil.copytree(out, dst)
    data = dst / "ugv" / "mav0" / "cam1" / "data"
    victims = sorted(data.glob("*.png"))[3:5]
    before = {p.name: p.read_bytes() for p in victims}
    for p in victims:
        p.unlink()
    (dst / "ugv" / COMPLETE_MARK).unlink()
    res = render_scenario(
        get_scenario("tiny"), dst, agents=AGENTS, duration=DURATION, progress=False, world=world
    )
    by = {r.agent_id: r for r in res.agents}
    assert by["uav1"].skipped and by["uav1"].rendered == 0
    assert not by["ugv"].skipped and by["ugv"].rendered == 2
    # deterministic: the re-rendered frames are byte-identical
    for p in victims:
        assert p.read_bytes() == before[p.name]


def test_cli_list_and_render(tmp_path: Path):
    from hivemap.sim.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["list"])
    assert res.exit_code == 0
    for n in [f"factory0{i}" for i in range(1, 9)] + ["tiny", "disjoint"]:
        assert n in res.output
    out = tmp_path / "cli"
    args = [
        "render",
        "--scenario",
        "tiny",
        "--out",
        str(out),
        "--agents",
        "ugv",
        "--duration",
        "1",
        "--no-progress",
    ]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "ugv: 11 stereo frames" in res.output
    assert len(list((out / "ugv" / "mav0" / "cam0" / "data").glob("*.png"))) == 11
    img = cv2.imread(str(next((out / "ugv" / "mav0" / "cam1" / "data").glob("*.png"))), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.shape == (240, 320)
    res = runner.invoke(app, args)
    assert res.exit_code == 0 and "skipped (complete)" in res.output
    res = runner.invoke(app, ["render", "--scenario", "nope", "--out", str(out)])
    assert res.exit_code != 0
    res = runner.invoke(app, ["render", "--scenario", "tiny", "--out", str(out), "--agents", "uav9"])
    assert res.exit_code != 0


def test_a_render_of_another_take_off_is_refused_not_reused(tmp_path: Path):
    # a render made before the presets got carriers and the climb take-off has the same name and seed:
    # the experiment runner must refuse it with a one-line error rather than run the old world
    import yaml

    from hivemap.eval.experiment import ensure_scenario
    from hivemap.sim.dataset import RenderMismatch, check_render, manifest_dict

    sc = get_scenario("factory01")
    assert sc.markers and sc.takeoff_climb_m > 0
    man = tmp_path / "factory01" / "manifest.yaml"
    man.parent.mkdir()
    done = {a.agent_id: {"complete": True} for a in sc.agents}
    old = manifest_dict(replace(sc, markers=False, takeoff_interval_s=0.0, takeoff_climb_m=0.0), done, None)
    for key in ("markers", "takeoff"):  # written before these keys existed
        old.pop(key)
    man.write_text(yaml.safe_dump(old))
    with pytest.raises(RenderMismatch, match="markers = False, not True"):
        ensure_scenario("factory01", tmp_path)
    # the carriers alone do not make it the same world: the take-off is checked too
    man.write_text(yaml.safe_dump({**old, "markers": True}))
    with pytest.raises(RenderMismatch, match="takeoff"):
        check_render(man, sc)
    man.write_text(yaml.safe_dump(manifest_dict(sc, done, None)))
    assert ensure_scenario("factory01", tmp_path) == man.parent  # the same world is reused as before
