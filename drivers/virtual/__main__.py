"""``python -m felis.drivers.virtual OPTIONS_JSON``: the child of `felis.drivers.virtual.process.spawn`."""

import sys

from felis.drivers.virtual.process import main

sys.exit(main())
