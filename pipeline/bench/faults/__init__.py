"""``seqat bench faults``: seeded faults (injection), their cases, the suite, the flight case and
the markdown report."""
