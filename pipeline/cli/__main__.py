"""``python -m pipeline.cli``: the ``seqat`` command (what ``seqat bench fuzz`` launches)."""

from pipeline.cli import app

app(prog_name="seqat")
