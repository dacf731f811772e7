"""Live dashboard of the running compensator (``fbgcomp serve --dashboard HOST:PORT``).

See :mod:`fbgcomp.dashboard.server` and docs/dashboard.md.
"""

from fbgcomp.dashboard.server import Dashboard, DashboardConfig, parse_listen

__all__ = ["Dashboard", "DashboardConfig", "parse_listen"]
