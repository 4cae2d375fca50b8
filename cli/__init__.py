"""The `hivemap` command line."""
