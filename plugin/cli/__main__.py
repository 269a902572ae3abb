"""``python -m hlbvh.cli``: the ``hlbvh`` command."""

import sys

from hlbvh.cli.command import main

sys.exit(main())
