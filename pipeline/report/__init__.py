"""Report: the paper's tables and figures from the evaluation artifacts, as Markdown and one
self-contained HTML page.

* :mod:`pipeline.report.analysis` -- teacher-prompt, teacher-domain and gate analyses (DataFrames);
* :mod:`pipeline.report.tables`   -- tables shaped like the paper's;
* :mod:`pipeline.report.figures`  -- figures drawn with OpenCV/numpy (no matplotlib);
* :mod:`pipeline.report.document` -- document model, Markdown and HTML rendering;
* :mod:`pipeline.report.glossary` -- the terms the report uses, defined once;
* :mod:`pipeline.report.build`    -- gathers the artifacts (missing ones are reported, not fatal).
"""
