"""Fixtures shared by the suites: two real Zenoh peers on loopback (tests/zenoh_peers.py), a
real PostgreSQL server (tests/postgres.py)."""

pytest_plugins = ("tests.zenoh_peers", "tests.postgres")
