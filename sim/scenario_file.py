"""Scenario files: a TOML file with the fields of a :class:`~hivemap.sim.scenarios.Scenario` preset.

A file may start from a preset (``preset = "factory01"``) and change any field; without ``preset`` it
must give every required field (``name``, ``description``, ``[[agents]]``). Tables ``[camera]``,
``[imu_noise]`` and ``[gnss_noise]`` change those fields one by one; ``[[agents]]`` replaces the agent list
(each with ``agent_id``, ``kind``, ``camera_pitch_deg``, ``path_length_m``, ``speed_mps``, ``baseline_m``
and optionally ``cruise_height_m`` and ``region``). An unknown key is an error naming it. Example::

    preset = "factory03"
    name = "factory03-dusk"
    seed = 11
    duration_s = 60.0
    [gnss_noise]
    sigma_horizontal = 0.1
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from hivemap.sim.conditions import LIGHTING, WEATHER
from hivemap.sim.scenarios import AgentSpec, CameraSpec, GnssNoise, ImuNoise, Scenario, get_scenario


class ScenarioError(ValueError):
    """A scenario file or name that cannot be used; the message names the file and the key."""


_TABLES: dict[str, type] = {"camera": CameraSpec, "imu_noise": ImuNoise, "gnss_noise": GnssNoise}


def _fields(cls: type) -> dict[str, dataclasses.Field[Any]]:
    return {f.name: f for f in dataclasses.fields(cls)}


def _coerce(value: Any, current: Any, where: str) -> Any:
    """TOML values into the field's type (ints where floats are expected, lists for tuples)."""
    if isinstance(current, bool) or isinstance(value, bool):
        if not isinstance(value, bool) or not isinstance(current, bool):
            raise ScenarioError(f"{where}: expected {type(current).__name__}, got {value!r}")
        return value
    if isinstance(current, float) or (current is None and isinstance(value, int | float)):
        if not isinstance(value, int | float):
            raise ScenarioError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if isinstance(current, tuple):
        if not isinstance(value, list) or len(value) != len(current):
            raise ScenarioError(f"{where}: expected a list of {len(current)} numbers, got {value!r}")
        return tuple(float(v) for v in value)
    if current is not None and not isinstance(value, type(current)):
        raise ScenarioError(f"{where}: expected {type(current).__name__}, got {value!r}")
    return value


def _update(obj: Any, values: dict[str, Any], where: str) -> Any:
    known = _fields(type(obj))
    changes = {}
    for k, v in values.items():
        if k not in known:
            raise ScenarioError(f"{where}: unknown key '{k}' (known: {', '.join(sorted(known))})")
        changes[k] = _coerce(v, getattr(obj, k), f"{where}.{k}")
    return dataclasses.replace(obj, **changes)


def _agent(values: Any, where: str) -> AgentSpec:
    if not isinstance(values, dict):
        raise ScenarioError(f"{where}: expected a table")
    known = _fields(AgentSpec)
    for k in values:
        if k not in known:
            raise ScenarioError(f"{where}: unknown key '{k}' (known: {', '.join(sorted(known))})")
    required = [n for n, f in known.items() if f.default is dataclasses.MISSING]
    missing = [n for n in required if n not in values]
    if missing:
        raise ScenarioError(f"{where}: missing {', '.join(missing)}")
    kind = values["kind"]
    if kind not in ("uav", "ugv"):
        raise ScenarioError(f"{where}.kind: 'uav' or 'ugv', got {kind!r}")
    floats = ("camera_pitch_deg", "path_length_m", "speed_mps", "baseline_m", "cruise_height_m")
    try:
        return AgentSpec(**{k: float(v) if k in floats else v for k, v in values.items()})
    except (TypeError, ValueError) as exc:
        raise ScenarioError(f"{where}: {exc}") from exc


def load_scenario_file(path: str | Path) -> Scenario:
    """The scenario a TOML file describes (see the module docstring); ScenarioError names what is wrong."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise ScenarioError(f"{p}: cannot read ({exc.strerror})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{p}: not valid TOML ({exc})") from exc
    preset = data.pop("preset", None)
    if preset is not None:
        try:
            base = get_scenario(str(preset))
        except KeyError as exc:
            raise ScenarioError(f"{p}: preset: {exc.args[0]}") from exc
    else:
        missing = [k for k in ("name", "description", "agents") if k not in data]
        if missing:
            raise ScenarioError(f"{p}: no preset, so it needs {', '.join(missing)}")
        base = Scenario(name="", description="", agents=())
    tables = {k: data.pop(k) for k in list(data) if k in _TABLES}
    agents = data.pop("agents", None)
    sc = _update(base, data, str(p))
    for k, v in tables.items():
        if not isinstance(v, dict):
            raise ScenarioError(f"{p}: [{k}] must be a table")
        sc = dataclasses.replace(sc, **{k: _update(getattr(sc, k), v, f"{p}: [{k}]")})
    if agents is not None:
        if not isinstance(agents, list) or not agents:
            raise ScenarioError(f"{p}: [[agents]] must list at least one agent")
        specs = tuple(_agent(a, f"{p}: agents[{i}]") for i, a in enumerate(agents))
        ids = [a.agent_id for a in specs]
        if len(set(ids)) != len(ids):
            raise ScenarioError(f"{p}: agent ids repeat: {ids}")
        sc = dataclasses.replace(sc, agents=specs)
    if sc.lighting not in LIGHTING:
        raise ScenarioError(f"{p}: lighting must be one of {sorted(LIGHTING)}, got {sc.lighting!r}")
    if sc.weather not in WEATHER:
        raise ScenarioError(f"{p}: weather must be one of {sorted(WEATHER)}, got {sc.weather!r}")
    return sc


def resolve_scenario(name_or_path: str, seed: int | None = None) -> Scenario:
    """A preset name or a ``.toml`` scenario file, with its world seed replaced by ``seed`` if given."""
    if name_or_path.endswith(".toml") or Path(name_or_path).is_file():
        sc = load_scenario_file(name_or_path)
    else:
        try:
            sc = get_scenario(name_or_path)
        except KeyError as exc:
            raise ScenarioError(str(exc.args[0])) from exc
    return sc if seed is None else dataclasses.replace(sc, seed=int(seed))
