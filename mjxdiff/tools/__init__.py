"""Other uses of the same engines and checks: the same sweep over several MJX releases
(``versions``), shrinking a divergence (``shrink``) into a bug report (``bundle``), Hypothesis
fuzzing (``fuzz``, ``strategies``), what the scenarios reach (``interactions``, ``coverage``),
Jacobians (``grad``), policies (``closedloop``) and performance (``bench``)."""
