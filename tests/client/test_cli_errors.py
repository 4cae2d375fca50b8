"""Errors a person can read: each ordinary mistake run through the real `hivemap` command ends with at
most 3 lines on stderr naming the culprit and a non-zero exit, without a traceback unless `-v`."""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hivemap.client.dataset import load_dataset


def _hivemap(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "hivemap.cli.main", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=cwd)


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _mistakes(tiny: Path, tmp: Path) -> list[tuple[str, list[str], str]]:
    """(what, hivemap arguments, text stderr must contain)."""
    empty = tmp / "not_a_dataset"
    empty.mkdir()
    trunc = _copy(tiny, tmp / "truncated")
    imu = trunc / "mav0" / "imu0" / "data.csv"
    text = imu.read_text()
    imu.write_text(text[: len(text) // 2])  # cut mid-line, as a copy interrupted half-way leaves it
    no_yaml = _copy(tiny, tmp / "no_yaml")
    (no_yaml / "mav0" / "cam1" / "sensor.yaml").unlink()
    corrupt = _copy(tiny, tmp / "corrupt")
    png = sorted((corrupt / "mav0" / "cam0" / "data").glob("*.png"))[3]
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00garbage" * 20)
    bad_markers = _copy(tiny, tmp / "bad_markers")
    (bad_markers / "markers.yaml").write_text("format_version: 1\ncarriers: [{agent_id: ugv}]\n")
    bad_toml = tmp / "bad.toml"
    bad_toml.write_text('port = 8765\n[tokens\nuav1 = "x"\n')
    bad_field = tmp / "bad_field.toml"
    bad_field.write_text('max_frame_bytes = "four megabytes"\n')
    offline = ["--offline", "--no-progress", "--out", str(tmp / "out")]
    return [
        ("missing dataset", ["agent", "--dataset", str(tmp / "nope"), *offline], str(tmp / "nope")),
        ("not a dataset", ["agent", "--dataset", str(empty), *offline], "no 'mav0' folder"),
        ("truncated imu0/data.csv", ["agent", "--dataset", str(trunc), *offline], str(imu)),
        ("missing sensor.yaml", ["agent", "--dataset", str(no_yaml), *offline], "cam1/sensor.yaml"),
        ("corrupt PNG", ["agent", "--dataset", str(corrupt), *offline], png.name),
        ("malformed markers.yaml", ["agent", "--dataset", str(bad_markers), *offline], "markers.yaml"),
        ("URL without scheme",
         ["agent", "--dataset", str(tiny), "--server", "localhost:8765", "--token", "t"], "--server"),
        ("live agent without an agent", ["agent", "--sim", "tiny", "--live", *offline], "SCENARIO:AGENT"),
        ("live agent the scenario lacks", ["agent", "--sim", "tiny:uav9", "--live", *offline], "uav9"),
        ("--sim without --live", ["agent", "--sim", "tiny:uav1", *offline], "--live"),
        ("bad TOML", ["server", "--config", str(bad_toml), "--port", "0"], "bad.toml: invalid TOML"),
        ("bad TOML value", ["server", "--config", str(bad_field), "--port", "0"], "field 'max_frame_bytes'"),
    ]  # fmt: skip


def test_each_mistake_prints_at_most_three_lines_naming_it(tiny_agent: Path, tmp_path: Path) -> None:
    failures = []
    for what, args, culprit in _mistakes(tiny_agent, tmp_path):
        res = _hivemap(*args, cwd=tmp_path)
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        # the log lines of a run that started are INFO/WARNING lines; the error itself is one line
        errors = [ln for ln in lines if " INFO " not in ln and " WARNING " not in ln]
        ok = (
            res.returncode != 0
            and len(errors) <= 3
            and culprit in res.stderr
            and "Traceback" not in res.stderr
        )
        if not ok:
            failures.append(f"{what}: exit {res.returncode}, stderr:\n{res.stderr[-2000:]}")
    assert not failures, "\n\n".join(failures)


def test_verbose_adds_the_traceback(tiny_agent: Path, tmp_path: Path) -> None:
    broken = _copy(tiny_agent, tmp_path / "no_yaml")
    (broken / "mav0" / "imu0" / "sensor.yaml").unlink()
    args = ["agent", "--dataset", str(broken), "--offline", "--no-progress", "--out", str(tmp_path / "o")]
    quiet, loud = _hivemap(*args, cwd=tmp_path), _hivemap("-v", *args, cwd=tmp_path)
    assert quiet.returncode == loud.returncode == 2
    assert quiet.stderr.strip().splitlines() == [
        f"hivemap: error: {broken}/mav0/imu0/sensor.yaml: file not found"
    ]
    assert "Traceback (most recent call last)" in loud.stderr and "DatasetError" in loud.stderr


def test_frames_listed_but_missing_on_disk_are_skipped(
    tiny_agent: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ds = _copy(tiny_agent, tmp_path / "partial")
    pngs = sorted((ds / "mav0" / "cam1" / "data").glob("*.png"))
    for p in (pngs[2], pngs[5]):
        p.unlink()
    with caplog.at_level(logging.WARNING):
        loaded = load_dataset(ds)
    assert len(loaded.frames) == len(pngs) - 2
    assert loaded.frames.t_ns.tolist() == [int(p.stem) for i, p in enumerate(pngs) if i not in (2, 5)]
    assert any("2 of 21 listed frames missing on disk, skipped" in r.getMessage() for r in caplog.records)
    assert any("cam0 frames without a cam1 partner dropped" in r.getMessage() for r in caplog.records)


def test_help_keeps_units_and_has_no_bool_placeholders() -> None:
    from typer.testing import CliRunner

    from hivemap.cli.main import app

    for cmd in (["agent"], ["server"], ["eval", "ate"], ["export", "mcap"], ["sim", "render"]):
        res = CliRunner().invoke(app, [*cmd, "--help"], terminal_width=120)
        assert res.exit_code == 0, res.output
        assert "<bool>" not in res.output, cmd
    ate_help = CliRunner().invoke(app, ["eval", "ate", "--help"], terminal_width=120).output
    assert "association [s]" in ate_help and "RPE distance [m]" in ate_help
    assert "[tokens]" in CliRunner().invoke(app, ["server", "--help"], terminal_width=120).output
