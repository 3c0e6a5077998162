"""``aesop demo``: the four hardware scenarios flown on a real stack, with a report."""
