"""Fakes for tests: real servers speaking real protocols, with deterministic answers."""
