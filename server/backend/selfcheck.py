"""Self-check of a map after each optimisation (issue 27): is the global map still what its measurements say?

* Per agent pair: at the keyframes where place recognition saw both agents at the same place (each
  accepted merge and loop between them, with its measured relative pose), how far the map's current
  relative pose of those two keyframes is from the measurement. An agent turned or shifted against the
  others after the merge shows up here while each agent's own trajectory looks fine.
* Per agent: the GNSS residuals of its keyframes' antennas against their fixes, in the map's frame when
  the map is in ENU, else after the best rigid fit of the whole map's antennas onto their fixes.

Pure functions over a map; the back-end runs them on the event loop after each optimisation, keeps the
last result per map (``/maps/{id}``: ``selfcheck``) and raises a ``selfcheck_alarm`` event per finding.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hivemap.maps.geometry import Sim3, rotation_angle_deg, se3_inverse
from hivemap.server.backend.fit import umeyama
from hivemap.server.backend.gnss import antenna_fixes
from hivemap.server.convert import split_folded

F64 = NDArray[np.float64]
KfKey = tuple[str, int]

# An agent pair whose measured relative pose is off by more than this in the map is an alarm (the
# accuracy every accepted loop and merge must have, issue 27).
PAIR_ALARM_M = 0.5
PAIR_ALARM_DEG = 2.0
# An agent whose GNSS residuals are larger than this many of its fixes' own sigmas (rms) is an alarm.
GNSS_ALARM_SIGMAS = 3.0


def pair_consistency(m: Any, records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per agent pair of map ``m`` (agent ids, sorted): the number of its accepted merges and loops still
    in the map, and the rms / largest translation (m) and largest rotation (deg) between each one's
    measured ``candidate_from_query`` and the map's current relative pose of its two keyframes."""
    by_pair: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for r in records:
        if "candidate_from_query" not in r or "query" not in r or "candidate" not in r:
            continue
        q, c = tuple(r["query"]), tuple(r["candidate"])
        kq, kc = m.keyframes.get(q), m.keyframes.get(c)
        if kq is None or kc is None:
            continue
        pair = tuple(sorted((split_folded(str(q[0]))[0], split_folded(str(c[0]))[0])))
        if pair[0] == pair[1]:
            continue
        meas = Sim3.from_matrix(np.asarray(r["candidate_from_query"], dtype=np.float64))
        cur = se3_inverse(np.asarray(kc.world_from_cam)) @ np.asarray(kq.world_from_cam)
        dt = float(np.linalg.norm(cur[:3, 3] - meas.t))
        dr = rotation_angle_deg(cur[:3, :3] @ meas.R.T)
        by_pair.setdefault((pair[0], pair[1]), []).append((dt, dr))
    out = []
    for (a, b), errs in sorted(by_pair.items()):
        t = np.array([e[0] for e in errs])
        out.append({"agents": [a, b], "n": len(errs), "rms_m": float(np.sqrt(np.mean(t**2))),
                    "max_m": float(t.max()), "max_deg": float(max(e[1] for e in errs))})  # fmt: skip
    return out


def gnss_residuals(m: Any, lever_of: Callable[[str], F64], enu: bool) -> dict[str, dict[str, Any]]:
    """Per agent (folded id) of map ``m``: how far its keyframes' antennas (camera pose and
    ``lever_of(agent)``, cam_from_antenna) are from their GNSS fixes: n, rms and largest (m), rms in
    units of the fixes' own sigmas. ``enu``: the map is in ENU; else the residuals are after the best
    rigid fit of all the map's antennas onto their fixes (none with fewer than 3 fixes)."""
    rows: list[tuple[str, F64, F64, float | None]] = []
    for k, ant, kf in antenna_fixes(m, lever_of):
        cov = getattr(kf, "gnss_cov", None)
        sig = None if cov is None else math.sqrt(max(float(np.trace(np.asarray(cov))) / 3.0, 1e-12))
        rows.append((k[0], ant, np.asarray(kf.gnss_enu, dtype=np.float64).reshape(3), sig))
    if not rows or (not enu and len(rows) < 3):
        return {}
    A, G = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    if not enu:
        A = umeyama(A, G, with_scale=False).apply(A)
    res = np.linalg.norm(A - G, axis=1)
    out: dict[str, dict[str, Any]] = {}
    for agent in sorted({r[0] for r in rows}):
        idx = [i for i, r in enumerate(rows) if r[0] == agent]
        e = res[idx]
        sigs = [rows[i][3] for i in idx]
        norm = None if any(s is None for s in sigs) else float(np.sqrt(np.mean((e / np.array(sigs)) ** 2)))
        out[agent] = {"n": len(idx), "rms_m": float(np.sqrt(np.mean(e**2))), "max_m": float(e.max()),
                      "rms_sigmas": norm, "frame": "enu" if enu else "fitted"}  # fmt: skip
    return out


def check(
    m: Any, records: Iterable[dict[str, Any]], lever_of: Callable[[str], F64], enu: bool
) -> dict[str, Any]:
    """Both checks of map ``m`` and their alarms (``subject``: the agent pair or "gnss <agent>", and a
    one-line ``message``)."""
    pairs, gnss = pair_consistency(m, records), gnss_residuals(m, lever_of, enu)
    alarms = [
        {"subject": "-".join(p["agents"]),
         "message": f"map {m.id}: {p['agents'][0]} and {p['agents'][1]} are {p['max_m']:.2f} m / "
                    f"{p['max_deg']:.1f} deg off their measured relative pose (limits {PAIR_ALARM_M} m / "
                    f"{PAIR_ALARM_DEG} deg)"}
        for p in pairs
        if p["max_m"] > PAIR_ALARM_M or p["max_deg"] > PAIR_ALARM_DEG
    ]  # fmt: skip
    alarms += [
        {"subject": f"gnss {a}",
         "message": f"map {m.id}: {a}'s GNSS residuals are {g['rms_sigmas']:.1f} sigmas rms "
                    f"({g['rms_m']:.2f} m, limit {GNSS_ALARM_SIGMAS})"}
        for a, g in gnss.items()
        if g["rms_sigmas"] is not None and g["rms_sigmas"] > GNSS_ALARM_SIGMAS
    ]  # fmt: skip
    return {"pairs": pairs, "gnss": gnss, "alarms": alarms}
