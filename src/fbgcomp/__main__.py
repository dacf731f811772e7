import sys

from fbgcomp.cli.app import main

sys.exit(main())
