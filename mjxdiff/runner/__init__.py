"""Running a sweep: scenarios end to end (``sweep``), in a watched child process (``guard``), as
the CLI runs it with known labels, history, baseline and files (``pipeline``), journalled unit
by unit (``journal``), on Ray (``executors``), and its scaling (``scaling``)."""
