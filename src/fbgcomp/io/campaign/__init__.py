"""Campaign folders (being split into modules by topic; this step only moves the file)."""

from fbgcomp.io.campaign.tables import *  # noqa: F401,F403
from fbgcomp.io.campaign.tables import (TIME_COLUMN, _meta_error, _MetaLoader,  # noqa: F401
                                        _read_meta)
from fbgcomp.io.campaign.tables import __doc__  # noqa: F401
