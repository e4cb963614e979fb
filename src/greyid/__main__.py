"""``python -m greyid`` is the ``greyid`` command."""

import sys

from .cli import main

sys.exit(main())
