"""Stage 4, output: verdicts -> text and report.json (``report``), report.html (``html_report``),
reproducers (``reproducer``), the run history (``history``) and what changed since a trusted run
(``baseline``)."""
