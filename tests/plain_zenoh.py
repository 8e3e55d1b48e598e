"""A plain eclipse-zenoh client for the tests (no fednav import: what any other client would do)."""

import json

import zenoh


def client(port: int) -> zenoh.Session:
    """Client-mode session to the service on loopback, multicast scouting off."""
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(c)
