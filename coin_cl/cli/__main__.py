"""`python -m coin_cl.cli`: the same as the `coin-cl` command."""

import sys

from coin_cl.cli import main

sys.exit(main())
