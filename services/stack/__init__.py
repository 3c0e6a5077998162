"""The stack as a product: ``aesop up``, ``aesop demo`` and the bus benchmark.

It starts and drives the services as processes over Zenoh and HTTP; it never
imports a service's internals.
"""
