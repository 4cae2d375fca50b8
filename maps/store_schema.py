"""The map store's SQLite schema and statements (:mod:`hivemap.maps.store` holds the code that uses them)."""

from __future__ import annotations

_TABLES = (
    "map_maps",
    "map_keyframes",
    "map_points",
    "map_loops",
    "map_redirects",
    "map_merges",
    "map_point_xyz",
)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS map_schema (version INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS map_state (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS map_meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS map_maps (
    map_id INTEGER PRIMARY KEY,
    agents TEXT NOT NULL DEFAULT '[]',    -- json list
    orphans TEXT NOT NULL DEFAULT '[]'    -- json list of [agent, id]
);
CREATE TABLE IF NOT EXISTS map_keyframes (
    map_id INTEGER NOT NULL,
    agent TEXT NOT NULL,
    id INTEGER NOT NULL,
    seq INTEGER NOT NULL,                 -- insertion order
    timestamp BLOB NOT NULL,              -- float64, 8 raw bytes
    world_from_cam BLOB NOT NULL,         -- packed arrays: dtype + shape + raw bytes
    camera TEXT NOT NULL,                 -- json (PinholeCamera.to_dict)
    keypoints BLOB NOT NULL,
    octaves BLOB NOT NULL,
    descriptors BLOB NOT NULL,
    point_ids BLOB NOT NULL,
    point_agents TEXT,                    -- json {keypoint index: agent} for other agents' points
    gnss_enu BLOB,
    gnss_cov BLOB,
    up_cam BLOB,
    u_right BLOB,                         -- float32 per keypoint, NaN = mono; NULL for a mono keyframe
    stereo_baseline REAL,
    odom_sigma BLOB,
    track_sigma BLOB,
    vio_from_cam BLOB,                    -- the agent's own pose of it (odometry frame), as last sent
    parent_agent TEXT,
    parent_id INTEGER,
    PRIMARY KEY (map_id, agent, id)
);
CREATE TABLE IF NOT EXISTS map_points (
    map_id INTEGER NOT NULL,
    agent TEXT NOT NULL,
    id INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    xyz BLOB NOT NULL,                    -- 3 float64 little-endian
    descriptor BLOB NOT NULL,             -- 32 bytes
    PRIMARY KEY (map_id, agent, id)
);
CREATE TABLE IF NOT EXISTS map_point_xyz (    -- positions written after a point's insertion (store_xyz)
    map_id INTEGER NOT NULL,
    agent TEXT NOT NULL,
    block INTEGER NOT NULL,               -- point id // BLOCK
    data BLOB NOT NULL,                   -- BLOCK bytes "slot set", then BLOCK x 3 float64 little-endian
    PRIMARY KEY (map_id, agent, block)
);
CREATE TABLE IF NOT EXISTS map_loops (
    map_id INTEGER NOT NULL,
    a_agent TEXT NOT NULL, a_id INTEGER NOT NULL,
    b_agent TEXT NOT NULL, b_id INTEGER NOT NULL,
    PRIMARY KEY (map_id, a_agent, a_id, b_agent, b_id)
);
CREATE TABLE IF NOT EXISTS map_redirects (
    map_id INTEGER NOT NULL,
    from_agent TEXT NOT NULL, from_id INTEGER NOT NULL,
    to_agent TEXT NOT NULL, to_id INTEGER NOT NULL,
    PRIMARY KEY (map_id, from_agent, from_id)
);
CREATE TABLE IF NOT EXISTS map_merges (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    map_id INTEGER NOT NULL,              -- the map whose merge_history holds the record
    record TEXT NOT NULL                  -- json
);
CREATE INDEX IF NOT EXISTS map_merges_map ON map_merges (map_id);
CREATE TABLE IF NOT EXISTS map_rendezvous (
    id INTEGER PRIMARY KEY,               -- the server's number of the observation
    record TEXT NOT NULL                  -- json: the message, its observer and its state
);
"""

_KF_COLS = (
    "map_id, agent, id, seq, timestamp, world_from_cam, camera, keypoints, octaves, descriptors, "
    "point_ids, point_agents, gnss_enu, gnss_cov, up_cam, u_right, stereo_baseline, odom_sigma, "
    "track_sigma, vio_from_cam, parent_agent, parent_id"
)
_KF_UPSERT = (
    f"INSERT INTO map_keyframes ({_KF_COLS}) VALUES ({', '.join('?' * 22)}) "
    "ON CONFLICT (map_id, agent, id) DO UPDATE SET timestamp = excluded.timestamp, "
    "world_from_cam = excluded.world_from_cam, camera = excluded.camera, keypoints = excluded.keypoints, "
    "octaves = excluded.octaves, descriptors = excluded.descriptors, point_ids = excluded.point_ids, "
    "point_agents = excluded.point_agents, gnss_enu = excluded.gnss_enu, gnss_cov = excluded.gnss_cov, "
    "up_cam = excluded.up_cam, u_right = excluded.u_right, stereo_baseline = excluded.stereo_baseline, "
    "odom_sigma = excluded.odom_sigma, track_sigma = excluded.track_sigma, "
    "vio_from_cam = excluded.vio_from_cam, "
    "parent_agent = excluded.parent_agent, parent_id = excluded.parent_id"
)
_PT_UPSERT = (
    "INSERT INTO map_points (map_id, agent, id, seq, xyz, descriptor) VALUES (?, ?, ?, ?, ?, ?) "
    "ON CONFLICT (map_id, agent, id) DO UPDATE SET xyz = excluded.xyz, descriptor = excluded.descriptor"
)
