"""``gdnav replay``: recorded inputs (``inputs``) re-run through the pipeline on one thread (``driver``)."""
