"""The map model shared by agents and server.

``from hivemap.maps import Keyframe, MapPoint, Map, MapStack`` (see ``hivemap.maps.model``).
"""

from hivemap.maps.model import (
    STRONG_COVISIBILITY,
    Keyframe,
    KfKey,
    Map,
    MapPoint,
    MapStack,
    PointKey,
    map_differences,
)

__all__ = [
    "STRONG_COVISIBILITY",
    "Keyframe",
    "KfKey",
    "Map",
    "MapPoint",
    "MapStack",
    "PointKey",
    "map_differences",
]
