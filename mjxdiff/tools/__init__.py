"""Other uses of the same engines and checks: the same sweep over several MJX releases
(``versions``), shrinking a divergence (``shrink``) into a bug report (``bundle``), Hypothesis
fuzzing (``fuzz``, ``strategies``: the model's parts in ``mjcf_spec``, their draws in ``mjcf_draws``),
what the scenarios reach (``interactions``, ``coverage``), Jacobians (``grad``), policies
(``closedloop``: loading them and their environments in ``policies``, the engines in closed loop in
``closedloop_streams``) and performance (``bench``)."""
