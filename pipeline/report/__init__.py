"""The report: the paper's tables and figures from the evaluation artifacts, as Markdown and one HTML page."""
