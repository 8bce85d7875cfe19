"""`python -m apose_studio.cli`: the same as the `apose` command."""

import sys

from apose_studio.cli.commands import main

sys.exit(main())
