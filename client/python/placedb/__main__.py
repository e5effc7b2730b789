"""``python3 -m placedb``: the placedb-py command line (placedb/cli.py)."""

import sys

from placedb.cli import main

sys.exit(main())
