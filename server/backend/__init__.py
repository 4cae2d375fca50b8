"""The collaboration back-end: place recognition, merges, loop closures, global optimisation, GNSS stage,
corrections; one module per stage.

* :mod:`.options`: the stages' options and presets (``[backend]`` in the server's TOML);
* :mod:`.scheduler`: :class:`Backend`, which only decides what runs when and applies results on the loop
  (the place-recognition worker, merges, loops); :mod:`.pipeline`: its optimisation pipeline;
* :mod:`.detect`: place recognition (BoW look-up + verification, :mod:`hivemap.server.placerec`);
* :mod:`.accept`: consistency of detections and the loops' sanity gates;
* :mod:`.fit`: a detection's transform (trimmed Umeyama, levelled by gravity, refined, its spread);
* :mod:`.surgery`: which map keeps its frame, fusing a loop's points, the merge and loop records;
* :mod:`.optimise`: pose graph and global BA;
* :mod:`.gnss`: the GNSS stage's inputs, acceptance and bend, and the GNSS-guided retry;
* :mod:`.corrections`: moving a map by corrections and the corrections sent to agents;
* :mod:`.rendezvous`: agents' observations of each other as edges and as merge evidence
  (:mod:`.rendezvous_fit`: their geometry).

Attached to a :class:`~hivemap.server.core.HiveServer` by :func:`install` (the app factory calls it when
``settings.backend.enabled``). Every candidate and rejection reason is published on ``/events``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hivemap.server.backend.options import PRESETS, BackendOptions, from_table, preset, to_table
from hivemap.server.backend.scheduler import Backend


def install(server: Any, options: BackendOptions | None = None) -> Backend:
    """Attach a back-end to ``server``: keyframe observer, startup and shutdown hooks. Without
    ``options``, the server settings' ``backend`` options (the default preset if it has none)."""
    if options is None:
        configured = getattr(getattr(server, "settings", None), "backend", None)
        options = configured if isinstance(configured, BackendOptions) else None
    backend = Backend(server, options)
    server.backend = backend
    server.keyframe_observers.append(backend.on_keyframe)
    if hasattr(server, "rendezvous_observers"):
        server.rendezvous_observers.append(backend.on_rendezvous)
    server.startup_hooks.append(backend.start)
    server.shutdown_hooks.append(backend.stop)
    if hasattr(server, "mission_end_observers"):
        server.mission_end_observers.append(backend.on_mission_end)
    return backend


def installer(options: BackendOptions) -> Callable[[Any], Backend]:
    """An ``extensions`` entry for ``create_app`` with non-default options."""
    return lambda server: install(server, options)


__all__ = ["PRESETS", "Backend", "BackendOptions", "from_table", "install", "installer", "preset", "to_table"]
