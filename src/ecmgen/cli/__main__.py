"""`python -m ecmgen.cli`: the `ecmgen` command."""

import sys

from . import main

sys.exit(main())
