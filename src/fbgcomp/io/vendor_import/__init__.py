"""Vendor and logger exports (being split into modules by topic; this step only moves the file)."""

from fbgcomp.io.vendor_import.mapping import *  # noqa: F401,F403
from fbgcomp.io.vendor_import.mapping import __doc__, describe  # noqa: F401
