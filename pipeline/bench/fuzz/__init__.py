"""``seqat bench fuzz``: seeded mutations of the sample flights (issue 13): ``mutations``
(what a case does to its copy of a flight), ``checks`` (absurd published outputs), ``suite``
(cases, commands as subprocesses, scores), ``report`` (fuzz.csv, fuzz.json, fuzz.md)."""
