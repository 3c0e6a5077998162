"""Slow reasoner: LLM prompts, strict answer parsing and the deadline-bound service."""
