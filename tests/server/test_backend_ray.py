"""The back-end with ``executor = "ray"``: the same end-to-end tests, verification as Ray tasks on a
local Ray instance (started once for the module). Skipped without Ray (``pip install hivemap[cluster]``)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ray = pytest.importorskip(
    "ray", reason="Ray is not installed (the optional extra: pip install hivemap[cluster])"
)

from test_backend import (  # noqa: E402
    Server,
    test_disjoint_agents_stay_in_two_maps,
    test_two_overlapping_agents_merge_in_ugv_frame,
)

from hivemap.server.backend import preset  # noqa: E402
from hivemap.server.backend.options import SchedulerOptions  # noqa: E402

__all__ = ["test_disjoint_agents_stay_in_two_maps", "test_two_overlapping_agents_merge_in_ugv_frame"]


@pytest.fixture(scope="module")
def local_ray() -> Iterator[Any]:
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


@pytest.fixture
def srv(tmp_path: Path, local_ray: Any) -> Iterator[Server]:
    opts = preset("monocular", scheduler=SchedulerOptions(executor="ray", workers=1, backlog=0))
    s = Server(tmp_path / "data", opts)
    assert s.backend.verifier.__class__.__name__ == "RayVerifier"
    yield s
    s.stop()
