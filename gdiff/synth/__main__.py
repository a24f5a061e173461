"""``python -m gdiff.synth OUT --preset NAME [--seed N] [--overwrite]``."""

import sys

from .writer import main

sys.exit(main())
