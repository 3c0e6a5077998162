"""Flights as MCAP files: recorded, replayed, imported into a cache and scored again.

``aesop record`` (the stack's Zenoh topics to a file), ``aesop replay``, ``aesop cache
import`` and ``aesop detector eval --recording``."""
