"""Two hosts on one machine and a lossy link between them, for tests and ``aesop bench link``.

The robot-to-server link as they impair it: :mod:`.proxy`."""
