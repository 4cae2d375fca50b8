"""The map model shared by agents and server."""
