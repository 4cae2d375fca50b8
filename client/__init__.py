"""The agent: dataset readers, front-end, second-stage fusion, server link.

``hivemap.client.Agent`` is the live-input API (feed stereo frames, IMU and GNSS; read the pose; get
the server's corrections), see :mod:`hivemap.client.agent`.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Agent", "AgentOptions", "CorrectionInfo", "FrameResult"]


def __getattr__(name: str) -> Any:
    # lazy: ``import hivemap.client.dataset`` (the bag reader, the CLI) should not load the front-end
    if name in __all__:
        from hivemap.client import agent

        return getattr(agent, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
