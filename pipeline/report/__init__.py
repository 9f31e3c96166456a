"""``seqat report``: the report model (:mod:`pipeline.report.model`), its HTML renderer
(:mod:`pipeline.report.html`) and the stage writing both (:mod:`pipeline.report.stage`)."""
