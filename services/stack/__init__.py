"""The stack as a product: ``aesop up``, ``aesop demo`` and the bus benchmark.

It starts the services as processes and drives them over Zenoh and HTTP. From
the services it borrows only pure data and pure functions (the scenario
loader, the hardware scene's texts), never a running part.
"""
