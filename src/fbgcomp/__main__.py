"""``python -m fbgcomp``: the ``fbgcomp`` command line (:func:`fbgcomp.cli.app.main`)."""

import sys

from fbgcomp.cli.app import main

sys.exit(main())
