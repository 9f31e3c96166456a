"""``seqat report``: the report model (:mod:`pipeline.report.model`), the check point
statistics and verdict (:mod:`pipeline.report.asprs`), the stages' warnings
(:mod:`pipeline.report.stage_warnings`), raster thumbnails and figures
(:mod:`pipeline.report.thumbnails`, :mod:`pipeline.report.figures`), the HTML and PDF
renderers (:mod:`pipeline.report.html`, :mod:`pipeline.report.pdf`) and the stage writing
them (:mod:`pipeline.report.stage`)."""
