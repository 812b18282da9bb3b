"""Paper-shaped tables and figures, one module per task, each drawn from the result tables only:
``report(results, summary, out_dir) -> str`` (Markdown). :mod:`dslearn.report` calls the module named
like the task."""
