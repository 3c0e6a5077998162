"""The robot-to-server link as tests and ``aesop bench link`` impair it: :mod:`.proxy`."""
