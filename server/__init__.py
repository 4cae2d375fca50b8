"""The hivemap server: ingest, map stack, collaboration back-end, REST, viewer."""
