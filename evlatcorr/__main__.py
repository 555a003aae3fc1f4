"""``python -m evlatcorr``: the command line."""

import sys

from evlatcorr.cli import main

sys.exit(main())
