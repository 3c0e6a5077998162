"""Test doubles that are real processes: ``aesop serve fake-llm``, an OpenAI-compatible server."""
