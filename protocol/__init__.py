"""Wire protocol v1: message dataclasses, msgpack codec, validation (numpy + msgpack only)."""
