"""``python -m felis`` is the ``felis`` command."""

import sys

from felis.cli.main import main

sys.exit(main())
