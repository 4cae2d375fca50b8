"""The back-end's options: the default preset is what the back-end used before its options were split by
stage, the server's TOML sets every option, and ``hivemap server --print-config`` round-trips."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from hivemap.server.backend import fit, pipeline, scheduler
from hivemap.server.backend.options import PRESETS, BackendOptions, ConfigError, from_table, preset, to_table
from hivemap.server.config_toml import settings_toml
from hivemap.server.settings import ServerSettings, load_settings

# The back-end's defaults before the split (``BackendOptions()`` of the single-module back-end, written
# down before any change): name -> value. PlaceRecOptions and GnssStageOptions were separate already.
TODAY: dict[str, Any] = {
    "ba_max_iterations": 30, "ba_max_keyframes": 4000, "consistency_max_gap": 8,
    "consistency_max_log_scale": 0.03, "consistency_max_rel_shift": 0.05, "consistency_max_rot_deg": 2.0,
    "consistency_required": 3, "correction_max_kfs": 50, "correction_min_move_m": 0.01,
    "correction_min_rot_deg": 0.1, "correction_stride": 12, "fix_scale": True, "gate_loop_candidates": True,
    "global_ba": None, "gnss": True, "gnss_agent_up": True, "gnss_cv_growth": 0.15, "gnss_cv_new_fixes": 3,
    "gnss_every_kfs": 1, "gnss_max_median_residual_m": 0.5, "gnss_max_rejected_ratio": 0.34,
    "gnss_retry_candidates": 6, "gnss_retry_interval_s": 5.0, "gnss_retry_radius_m": 10.0,
    "level_depth_weighted": True, "level_gravity": True, "level_reprojection": True, "level_up_window": 6,
    "loop_max_correction_deg": 5.0, "loop_max_correction_m": 1.0, "loop_max_gravity_deg": 1.0,
    "loop_sigma_bootstrap": 30, "min_pair_inlier_ratio": 0.5, "pose_graph": True,
    "pose_graph_max_move_m": 3.0, "pose_graph_sigma_rot": 0.01, "pose_graph_sigma_trans": 0.05,
    "pose_graph_sigma_yaw": None, "queue_max": 5000, "transform_window": 20,
    "placerec": {
        "bow_max_distance": 50, "bow_ratio": 0.75, "consistency_max_gap": 8,
        "consistency_max_log_scale": 0.05, "consistency_max_rel_shift": 0.05, "consistency_max_rot_deg": 3.0,
        "consistency_required": 1, "covisible_window": 5, "feasibility_ratio": 0.3,
        "gnss_retry_thresholds": {"min_inliers": 10, "min_matches": 12, "min_projected": 25},
        "huber_px": 2.45, "inlier_chi2": 9.21, "loop_max_correction_deg": 0.0, "loop_max_correction_m": 0.0,
        "max_refine_rot_deg": 10.0, "max_scale": 20.0, "max_verifications": 64, "metric_max_log_scale": 0.15,
        "min_scale": 0.05, "ransac_min_error": 0.01, "ransac_min_trials": 200, "ransac_rel_error": 0.03,
        "refine_depth_sigma_rel": 0.02, "refine_max_points": 300, "search_max_distance": 50,
        "search_radius_px": 8.0, "thresholds": {"min_inliers": 20, "min_matches": 20, "min_projected": 40},
        "use_feasibility": True,
    },
    "gnss_stage": {
        "cv_folds": 5, "cv_min_fixes": 10, "gravity_aligned": True, "huber_k": 1.345, "max_iterations": 50,
        "min_fixes": 3, "min_spread_m": 5.0, "outlier_sigma": 10.0, "sigma_attitude": 0.005,
        "stiffness_scales": (1.0, 0.3, 0.1, 0.03),
    },
}  # fmt: skip

# where each old option lives now: (stage, field); stage None = BackendOptions itself
MOVED: dict[str, tuple[str | None, str]] = {
    "queue_max": ("scheduler", "queue_max"),
    "fix_scale": (None, "fix_scale"), "gnss": ("gnss", "enabled"),
    "ba_max_iterations": ("optimise", "ba_max_iterations"),
    "ba_max_keyframes": ("optimise", "ba_max_keyframes"),
    "pose_graph_max_move_m": ("optimise", "pose_graph_max_move_m"),
    "pose_graph_sigma_rot": ("optimise", "pose_graph_sigma_rot"),
    "pose_graph_sigma_trans": ("optimise", "pose_graph_sigma_trans"),
    "correction_max_kfs": ("corrections", "max_kfs"), "correction_min_move_m": ("corrections", "min_move_m"),
    "correction_min_rot_deg": ("corrections", "min_rot_deg"), "correction_stride": ("corrections", "stride"),
    "transform_window": ("corrections", "transform_window"),
    "gnss_cv_growth": ("gnss", "cv_growth"), "gnss_cv_new_fixes": ("gnss", "cv_new_fixes"),
    "gnss_max_median_residual_m": ("gnss", "max_median_residual_m"),
    "gnss_max_rejected_ratio": ("gnss", "max_rejected_ratio"),
    "gnss_retry_candidates": ("gnss", "retry_candidates"),
    "gnss_retry_interval_s": ("gnss", "retry_interval_s"), "gnss_retry_radius_m": ("gnss", "retry_radius_m"),
    "level_gravity": ("fit", "level_gravity"), "level_reprojection": ("fit", "level_reprojection"),
    "level_up_window": ("fit", "level_up_window"), "loop_sigma_bootstrap": ("fit", "loop_sigma_bootstrap"),
    **{k: ("accept", k) for k in (
        "consistency_max_gap", "consistency_max_log_scale", "consistency_max_rel_shift",
        "consistency_max_rot_deg",
        "consistency_required", "min_pair_inlier_ratio", "loop_max_correction_deg", "loop_max_correction_m",
        "loop_max_gravity_deg")},
}  # fmt: skip


# knobs removed as options (always on, or set by no one): constants now
GONE = ("gate_loop_candidates", "gnss_agent_up", "pose_graph", "gnss_every_kfs", "level_depth_weighted")


def _keys(table: dict[str, Any]) -> list[str]:
    out = []
    for k, v in table.items():
        out += [k, *(_keys(v) if isinstance(v, dict) else [])]
    return out


def _plain(v: Any) -> Any:
    return dataclasses.asdict(v) if dataclasses.is_dataclass(v) and not isinstance(v, type) else v


def test_default_preset_equals_the_defaults_before_the_split() -> None:
    o = preset("default")
    assert o == BackendOptions() == PRESETS["default"]
    for old, (stage, name) in MOVED.items():
        holder = o if stage is None else getattr(o, stage)
        assert getattr(holder, name) == TODAY[old], old
    # options added since the split (issue 23: candidates verified once per covisibility group, what a
    # look-up retrieves independent of the team; its verification budget and 4 x agents are gone; two-phase
    # verification and the rigid-consensus pre-test)
    added = {"group_covisible": 10, "group_min_ratio": 0.75, "retrieve_max": 16, "max_groups": 3,
             "two_phase": True, "consensus_pretest": True}  # fmt: skip
    plain = _plain(o.placerec)
    assert {k: plain.pop(k) for k in added} == added
    assert plain == TODAY["placerec"]
    assert _plain(o.gnss.stage) == TODAY["gnss_stage"]
    # None = "global BA for Sim(3) maps only": the metric default has it off, the monocular preset on
    assert o.optimise.global_ba is False and o.fix_scale is True
    assert PRESETS["monocular"].optimise.global_ba is True and PRESETS["monocular"].fix_scale is False
    assert o.optimise.pose_graph_sigma_yaw == 0.0  # None (isotropic) is now 0
    # knobs no one set are constants now, at the value they always had
    assert TODAY["gnss_every_kfs"] == scheduler.GNSS_EVERY_KFS
    assert fit.DEPTH_WEIGHTED is TODAY["level_depth_weighted"]
    assert pipeline.POSE_GRAPH_ANCHORS_PER_AGENT == 1
    names = set(_keys(to_table(o)))
    assert not names & set(GONE), names & set(GONE)
    mapped = set(MOVED) | {"placerec", "gnss_stage", "global_ba", "pose_graph_sigma_yaw", *GONE}
    assert mapped == set(TODAY)


def test_tables_override_the_preset_and_unknown_keys_are_named() -> None:
    o = from_table(
        {"preset": "monocular", "accept": {"loop_max_gravity_deg": 2}, "gnss": {"stage": {"cv_folds": 3}}}
    )
    assert o.preset == "monocular" and o.fix_scale is False and o.optimise.global_ba is True
    assert o.accept.loop_max_gravity_deg == 2.0 and isinstance(o.accept.loop_max_gravity_deg, float)
    assert o.gnss.stage.cv_folds == 3 and o.accept.consistency_required == 3
    assert from_table(False) == dataclasses.replace(BackendOptions(), enabled=False)
    with pytest.raises(ConfigError, match=r"^unknown key backend\.placerec\.thresholds\.min_inlier$"):
        from_table({"placerec": {"thresholds": {"min_inlier": 3}}})
    with pytest.raises(ConfigError, match="unknown back-end preset 'stereo'"):
        from_table({"preset": "stereo"})
    with pytest.raises(ConfigError, match=r"backend\.fit\.level_up_window: expected an integer"):
        from_table({"fit": {"level_up_window": 1.5}})
    assert from_table(to_table(o)) == o


def test_print_config_round_trips(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hivemap.cli.main import app

    for k in [k for k in __import__("os").environ if k.startswith("HIVEMAP_")]:
        monkeypatch.delenv(k)
    cfg = tmp_path / "server.toml"
    cfg.write_text(
        'port = 9000\n[tokens]\nuav1 = "s3cret"\n[start_poses]\n'
        "uav1 = [[1,0,0,0.5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]\n"
        '[backend]\npreset = "monocular"\n[backend.gnss]\nretry_radius_m = 4\n[backend.gnss.stage]\n'
        "stiffness_scales = [1.0, 0.1]\n[backend.placerec.thresholds]\nmin_inliers = 25\n"
    )
    runner = CliRunner()
    first = runner.invoke(app, ["server", "--config", str(cfg), "--print-config"])
    assert first.exit_code == 0, first.output
    printed = tmp_path / "printed.toml"
    printed.write_text(first.output)
    settings = load_settings(cfg)
    again = load_settings(printed)
    assert again == settings
    assert again.backend.gnss.stage.stiffness_scales == (1.0, 0.1)
    assert again.backend.placerec.thresholds.min_inliers == 25 and again.backend.gnss.retry_radius_m == 4.0
    second = runner.invoke(app, ["server", "--config", str(printed), "--print-config"])
    assert second.output == first.output
    assert settings_toml(ServerSettings()) != first.output


def test_unknown_key_gives_one_line_error(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[backend.accept]\nloop_max_gravity = 2.0\n")
    # the real command: its error handler turns known errors into one line and exit code 2
    res = subprocess.run(
        [sys.executable, "-m", "hivemap.cli.main", "server", "--config", str(cfg), "--print-config"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 2, res.stderr
    (line,) = res.stderr.strip().splitlines()
    assert line.endswith("bad.toml: unknown key backend.accept.loop_max_gravity"), line
