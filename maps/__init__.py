"""The map model shared by agents and server.

``from hivemap.maps import Keyframe, MapPoint, Map, MapStack`` (see ``hivemap.maps.model`` and
``hivemap.maps.stack``).
"""

from hivemap.maps.model import (
    STRONG_COVISIBILITY,
    Keyframe,
    KfKey,
    Map,
    MapPoint,
    PointKey,
    map_differences,
)
from hivemap.maps.stack import MapStack

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
