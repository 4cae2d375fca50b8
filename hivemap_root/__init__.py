"""hivemap: centralized collaborative visual(-inertial) SLAM for teams of UAVs and UGVs."""

__version__ = "0.1.0"
