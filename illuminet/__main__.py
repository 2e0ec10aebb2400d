"""`python -m illuminet` is the `illuminet` command."""

import sys

from illuminet.cli import main

sys.exit(main())
