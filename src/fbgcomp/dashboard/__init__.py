"""Live dashboard of the running compensator (``fbgcomp serve --dashboard [HOST:]PORT``).

See :mod:`fbgcomp.dashboard.server`, docs/dashboard.md and docs/security.md.
"""

from fbgcomp.dashboard.server import Dashboard, DashboardConfig
from fbgcomp.dashboard.transport import is_loopback, parse_listen

__all__ = ["Dashboard", "DashboardConfig", "is_loopback", "parse_listen"]
