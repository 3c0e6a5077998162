"""The AESOP services: each package is one process (settings, schemas, routes, api,
worker, client)."""
