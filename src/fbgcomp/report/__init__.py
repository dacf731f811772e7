"""``fbgcomp report``: figures and the self-contained HTML report."""
