"""``seqat simulate``: simulated flights written as flight folders (observations or rendered)."""
