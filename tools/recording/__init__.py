"""Flights as MCAP files: ``aesop record`` (the stack's Zenoh topics to a file)."""
