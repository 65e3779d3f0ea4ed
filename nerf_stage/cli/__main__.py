"""``python -m nerf_stage.cli``: the ``nerf-stage`` command."""

import sys

from . import main

sys.exit(main())
