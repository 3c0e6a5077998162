"""Fixtures shared by the suites: two real Zenoh peers on loopback (tests/zenoh_peers.py)."""

pytest_plugins = ("tests.zenoh_peers",)
