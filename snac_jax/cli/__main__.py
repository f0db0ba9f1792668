"""`python -m snac_jax.cli` runs the `snac` command."""

import sys

from snac_jax.cli import main

sys.exit(main())
