"""``python -m lfcam`` = the ``lfcam`` command."""

import sys

from lfcam.cli.main import main

sys.exit(main())
